/*
 * Gray–Scott reaction–diffusion with MPI, pushing each rank's brick of V and U to a
 * generator-node as named fields of a Blueprint-shaped mesh (insitu_push_mesh) through the
 * insitu C client (client-c/include/insitu.h).
 *
 * The model is the ADIOS2 tutorial's, as in core/src/volume/gray_scott.rs: Du = 0.2, Dv = 0.1,
 * F = 0.01, k = 0.05, dt = 2, a 7-point Laplacian divided by 6, periodic boundaries, u = 1 and
 * v = 0 except a centred cube of side 12 (u = 0.25, v = 0.33), noise 1e-7 from a SplitMix64
 * hash of (seed, step, global cell). Every cell is computed the same way whatever the
 * decomposition, so any number of ranks gives the same field as one (and as the Rust model).
 *
 * Decomposition: MPI_Dims_create over a periodic 3-D Cartesian communicator; each rank owns
 * a block of the N³ grid and exchanges one halo layer with its six face neighbours before
 * every step. Every EVERY steps each rank pushes its owned voxels plus the first halo plane on
 * the upper side of each axis where it is not the last block: neighbouring bricks then share
 * their boundary plane, which is how the viz-node composes one picture (docs/conventions.md, "A world of ranks").
 *
 * Usage: mpirun -np P gray_scott_mpi GENERATOR_ADDR N STEPS EVERY
 *   e.g. mpirun -np 4 gray_scott_mpi 127.0.0.1:50051 64 400 100
 * The token, if the generator-node needs one, comes from INSITU_TOKEN.
 */
#include <mpi.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "insitu.h"

#define DU 0.2
#define DV 0.1
#define FEED 0.01
#define KILL 0.05
#define DT 2.0
#define NOISE 1e-7
#define SEED 0x5eed2026ULL
#define SEED_HALF 6

static double uniform_pm1(uint64_t seed, uint64_t step, uint64_t cell) {
    uint64_t z = seed ^ (step * 0x9e3779b97f4a7c15ULL) ^ (cell * 0xd1b54a32d192ed03ULL);
    z = (z ^ (z >> 30)) * 0xbf58476d1ce4e5b9ULL;
    z = (z ^ (z >> 27)) * 0x94d049bb133111ebULL;
    z ^= z >> 31;
    return (double)(z >> 11) * (2.0 / (double)(1ULL << 53)) - 1.0;
}

/* A block with one ghost layer on each side: local index of (x, y, z) in [-1, n]. */
typedef struct {
    int n[3];     /* owned cells per axis */
    int o[3];     /* first owned global index per axis */
    double *u, *v, *u2, *v2;
} Block;

static size_t at(const Block *b, int x, int y, int z) {
    return (size_t)(x + 1) + (size_t)(b->n[0] + 2) * ((size_t)(y + 1) + (size_t)(b->n[1] + 2) * (size_t)(z + 1));
}

/* Exchanges the ghost layers of `f` with the six face neighbours (x, then y, then z, each
 * including the ghosts of the previous axes, so edges and corners are right too). */
static void exchange(const Block *b, double *f, MPI_Comm cart) {
    int lo[3] = {-1, -1, -1}, hi[3] = {b->n[0], b->n[1], b->n[2]};
    for (int axis = 0; axis < 3; axis++) {
        int a1 = (axis + 1) % 3, a2 = (axis + 2) % 3;
        int m1 = b->n[a1] + 2, m2 = b->n[a2] + 2;
        size_t count = (size_t)m1 * (size_t)m2;
        double *send = malloc(count * sizeof(double)), *recv = malloc(count * sizeof(double));
        int down, up;
        MPI_Cart_shift(cart, axis, 1, &down, &up);
        for (int dir = 0; dir < 2; dir++) {
            /* dir 0: send my last owned plane up, receive my lower ghost from below. */
            int src_plane = dir == 0 ? b->n[axis] - 1 : 0;
            int dst_plane = dir == 0 ? -1 : b->n[axis];
            int to = dir == 0 ? up : down, from = dir == 0 ? down : up;
            size_t k = 0;
            for (int j = lo[a2]; j <= hi[a2]; j++)
                for (int i = lo[a1]; i <= hi[a1]; i++) {
                    int c[3];
                    c[axis] = src_plane; c[a1] = i; c[a2] = j;
                    send[k++] = f[at(b, c[0], c[1], c[2])];
                }
            MPI_Sendrecv(send, (int)count, MPI_DOUBLE, to, 0, recv, (int)count, MPI_DOUBLE, from, 0,
                         cart, MPI_STATUS_IGNORE);
            k = 0;
            for (int j = lo[a2]; j <= hi[a2]; j++)
                for (int i = lo[a1]; i <= hi[a1]; i++) {
                    int c[3];
                    c[axis] = dst_plane; c[a1] = i; c[a2] = j;
                    f[at(b, c[0], c[1], c[2])] = recv[k++];
                }
        }
        free(send);
        free(recv);
        (void)m1;
        (void)m2;
    }
}

static void step_once(Block *b, int N, uint64_t step) {
    for (int z = 0; z < b->n[2]; z++)
        for (int y = 0; y < b->n[1]; y++)
            for (int x = 0; x < b->n[0]; x++) {
                size_t i = at(b, x, y, z);
                double *u = b->u, *v = b->v;
#define LAP(s) ((s[at(b, x - 1, y, z)] + s[at(b, x + 1, y, z)] + s[at(b, x, y - 1, z)] + \
                 s[at(b, x, y + 1, z)] + s[at(b, x, y, z - 1)] + s[at(b, x, y, z + 1)] - 6.0 * s[i]) / 6.0)
                double tu = u[i], tv = v[i];
                double uvv = tu * tv * tv;
                double du = DU * LAP(u) - uvv + FEED * (1.0 - tu);
                double dv = DV * LAP(v) + uvv - (FEED + KILL) * tv;
                uint64_t gx = (uint64_t)(b->o[0] + x), gy = (uint64_t)(b->o[1] + y), gz = (uint64_t)(b->o[2] + z);
                uint64_t cell = gx + (uint64_t)N * (gy + (uint64_t)N * gz);
                du += NOISE * uniform_pm1(SEED, step, cell);
                b->u2[i] = tu + du * DT;
                b->v2[i] = tv + dv * DT;
#undef LAP
            }
    double *t = b->u; b->u = b->u2; b->u2 = t;
    t = b->v; b->v = b->v2; b->v2 = t;
}

static int check(InsituStatus s, const char *what, int rank) {
    if (s != INSITU_STATUS_OK) {
        fprintf(stderr, "rank %d: %s failed (%d): %s\n", rank, what, (int)s, insitu_last_error());
        return 1;
    }
    return 0;
}

int main(int argc, char **argv) {
    MPI_Init(&argc, &argv);
    int rank, size;
    MPI_Comm_rank(MPI_COMM_WORLD, &rank);
    MPI_Comm_size(MPI_COMM_WORLD, &size);
    if (argc != 5) {
        if (rank == 0) fprintf(stderr, "usage: %s GENERATOR_ADDR N STEPS EVERY\n", argv[0]);
        MPI_Finalize();
        return 2;
    }
    const char *addr = argv[1];
    int N = atoi(argv[2]), steps = atoi(argv[3]), every = atoi(argv[4]);
    if (N < 2 * SEED_HALF || steps < 1 || every < 1) {
        if (rank == 0) fprintf(stderr, "need N >= 12, STEPS >= 1, EVERY >= 1\n");
        MPI_Finalize();
        return 2;
    }
    int dims[3] = {0, 0, 0}, periods[3] = {1, 1, 1}, coords[3];
    MPI_Dims_create(size, 3, dims);
    MPI_Comm cart;
    MPI_Cart_create(MPI_COMM_WORLD, 3, dims, periods, 0, &cart);
    MPI_Cart_coords(cart, rank, 3, coords);
    /* MPI_Dims_create orders dims decreasing; our x is the first axis of the grid. */
    Block b;
    for (int a = 0; a < 3; a++) {
        b.o[a] = (int)((long)coords[a] * N / dims[a]);
        b.n[a] = (int)((long)(coords[a] + 1) * N / dims[a]) - b.o[a];
    }
    size_t cells = (size_t)(b.n[0] + 2) * (size_t)(b.n[1] + 2) * (size_t)(b.n[2] + 2);
    b.u = malloc(cells * sizeof(double)); b.v = malloc(cells * sizeof(double));
    b.u2 = malloc(cells * sizeof(double)); b.v2 = malloc(cells * sizeof(double));
    for (int z = -1; z <= b.n[2]; z++)
        for (int y = -1; y <= b.n[1]; y++)
            for (int x = -1; x <= b.n[0]; x++) {
                int g[3] = {b.o[0] + x, b.o[1] + y, b.o[2] + z};
                int inside = 1;
                for (int a = 0; a < 3; a++) {
                    int c = ((g[a] % N) + N) % N;
                    inside &= c >= N / 2 - SEED_HALF && c < N / 2 + SEED_HALF;
                }
                size_t i = at(&b, x, y, z);
                b.u[i] = inside ? 0.25 : 1.0;
                b.v[i] = inside ? 0.33 : 0.0;
            }
    memcpy(b.u2, b.u, cells * sizeof(double));
    memcpy(b.v2, b.v, cells * sizeof(double));

    InsituClient *client = NULL;
    int failed = check(insitu_connect(addr, NULL, &client), "insitu_connect", rank);
    /* The pushed brick: owned voxels plus the upper halo plane where a neighbour follows. */
    uint32_t global[3] = {(uint32_t)N, (uint32_t)N, (uint32_t)N}, offset[3], bdims[3];
    for (int a = 0; a < 3; a++) {
        offset[a] = (uint32_t)b.o[a];
        bdims[a] = (uint32_t)b.n[a] + (coords[a] + 1 < dims[a] ? 1u : 0u);
    }
    size_t voxels = (size_t)bdims[0] * bdims[1] * bdims[2];
    /* Both species as named fields of a Blueprint-shaped mesh; the generator-node renders the
     * one its scene names (by default the first, v) and skips the other. */
    float *fv = malloc(voxels * sizeof(float)), *fu = malloc(voxels * sizeof(float));
    InsituField fields[2] = {
        {"v", INSITU_ASSOCIATION_VERTEX, INSITU_DTYPE_F32, fv, voxels * sizeof(float)},
        {"u", INSITU_ASSOCIATION_VERTEX, INSITU_DTYPE_F32, fu, voxels * sizeof(float)},
    };
    InsituMesh mesh = {
        .origin = {0.0f, 0.0f, 0.0f},
        .spacing = {1.0f, 1.0f, 1.0f},
        .rank = (uint32_t)rank,
        .world_size = (uint32_t)size,
        .fields = fields,
        .num_fields = 2,
    };
    for (int a = 0; a < 3; a++) {
        mesh.global_dims[a] = global[a];
        mesh.brick_offset[a] = offset[a];
        mesh.brick_dims[a] = bdims[a];
    }
    for (int s = 1; s <= steps && !failed; s++) {
        exchange(&b, b.u, cart);
        exchange(&b, b.v, cart);
        step_once(&b, N, (uint64_t)(s - 1));
        if (s % every == 0) {
            exchange(&b, b.u, cart);
            exchange(&b, b.v, cart);
            size_t k = 0;
            for (uint32_t z = 0; z < bdims[2]; z++)
                for (uint32_t y = 0; y < bdims[1]; y++)
                    for (uint32_t x = 0; x < bdims[0]; x++, k++) {
                        size_t i = at(&b, (int)x, (int)y, (int)z);
                        fv[k] = (float)b.v[i];
                        fu[k] = (float)b.u[i];
                    }
            failed = check(insitu_push_mesh(client, (uint64_t)s, (double)s * DT, &mesh, NULL),
                           "insitu_push_mesh", rank);
        }
        /* One rank failing stops all: a simulation would not go on half-observed. */
        MPI_Allreduce(MPI_IN_PLACE, &failed, 1, MPI_INT, MPI_MAX, cart);
    }
    InsituNodeStatus st;
    if (client != NULL) failed |= check(insitu_close(&client, 600.0, &st), "insitu_close", rank);
    if (rank == 0 && !failed)
        printf("gray-scott %d^3, %d ranks (%dx%dx%d), %d steps: pushed every %d; node received %llu, shipped %llu\n",
               N, size, dims[0], dims[1], dims[2], steps, every, (unsigned long long)st.steps_received,
               (unsigned long long)st.steps_shipped);
    free(fv); free(fu);
    free(b.u); free(b.v); free(b.u2); free(b.v2);
    MPI_Comm_free(&cart);
    MPI_Finalize();
    return failed ? 1 : 0;
}
