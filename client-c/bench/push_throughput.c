/*
 * The C client's push throughput: PUSHES pushes of an N³ float field to a generator-node,
 * after one warm-up push; prints GB/s (a push returns once the node has queued the step).
 * Built and run by `cargo bench -p insitu-e2e --bench pipeline` beside the Rust client's.
 *
 * Usage: push_throughput GENERATOR_ADDR N PUSHES
 */
#include <stdio.h>
#include <stdlib.h>
#include <time.h>

#include "insitu.h"

int main(int argc, char **argv) {
    if (argc != 4) {
        fprintf(stderr, "usage: %s GENERATOR_ADDR N PUSHES\n", argv[0]);
        return 2;
    }
    uint32_t n = (uint32_t)atoi(argv[2]);
    int pushes = atoi(argv[3]);
    size_t voxels = (size_t)n * n * n;
    float *field = malloc(voxels * sizeof(float));
    if (field == NULL) return 1;
    for (size_t i = 0; i < voxels; i++) field[i] = (float)(i % 977);
    uint32_t dims[3] = {n, n, n}, zero[3] = {0, 0, 0};
    InsituClient *c = NULL;
    if (insitu_connect(argv[1], NULL, &c) != INSITU_STATUS_OK) {
        fprintf(stderr, "connect: %s\n", insitu_last_error());
        return 1;
    }
    struct timespec t0, t1;
    for (int k = 0; k <= pushes; k++) {
        if (k == 1) clock_gettime(CLOCK_MONOTONIC, &t0);
        if (insitu_push_step(c, (uint64_t)k, (double)k, field, voxels * sizeof(float), INSITU_DTYPE_F32,
                             dims, zero, dims, NULL, 0, 1, NULL) != INSITU_STATUS_OK) {
            fprintf(stderr, "push: %s\n", insitu_last_error());
            return 1;
        }
    }
    clock_gettime(CLOCK_MONOTONIC, &t1);
    double secs = (double)(t1.tv_sec - t0.tv_sec) + 1e-9 * (double)(t1.tv_nsec - t0.tv_nsec);
    double bytes = (double)voxels * sizeof(float);
    printf("ingest (C client): %d pushes of %.0f MiB in %.2f s = %.2f GB/s\n", pushes,
           bytes / (1 << 20), secs, pushes * bytes / secs / 1e9);
    insitu_close(&c, 60.0, NULL);
    free(field);
    return 0;
}
