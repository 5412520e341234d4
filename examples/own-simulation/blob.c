#include <math.h>
#include <stdio.h>
#include "insitu.h"

enum { N = 64, STEPS = 10 };
static float field[N * N * N];                            /* x varies fastest */

int main(int argc, char **argv) {
    InsituClient *c = NULL;
    const uint32_t dims[3] = {N, N, N}, offset[3] = {0, 0, 0};
    if (argc < 2 || insitu_connect(argv[1], NULL, &c) != INSITU_STATUS_OK) goto fail;
    for (int step = 0; step < STEPS; step++) {
        float cx = 16.0f + 2.0f * step;                   /* a blob moving along x */
        for (int z = 0; z < N; z++)
            for (int y = 0; y < N; y++)
                for (int x = 0; x < N; x++) {
                    float r2 = (x - cx) * (x - cx) + (y - 32.0f) * (y - 32.0f) + (z - 32.0f) * (z - 32.0f);
                    field[(z * N + y) * N + x] = expf(-r2 / 128.0f);
                }
        if (insitu_push_step(c, step, 0.1 * step, field, sizeof field, INSITU_DTYPE_F32,
                             dims, offset, dims, NULL, 0, 1, NULL) != INSITU_STATUS_OK) goto fail;
    }
    if (insitu_close(&c, 600.0, NULL) != INSITU_STATUS_OK) goto fail;  /* flush: all stored */
    printf("pushed %d steps of %d^3\n", STEPS, N);
    return 0;
fail:
    fprintf(stderr, "insitu: %s\n", argc < 2 ? "usage: blob HOST:PORT" : insitu_last_error());
    return 1;
}
