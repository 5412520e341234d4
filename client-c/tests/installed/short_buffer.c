/* A buffer shorter than the brick its dtype claims (floats declared as doubles), pushed with
 * its true byte length: the push is refused before the buffer is read, which valgrind checks
 * (tests/tests/e2e/install.rs). Then a push on the handle insitu_close nulled. */
#include <stdio.h>
#include <stdlib.h>
#include "insitu.h"

int main(int argc, char **argv) {
    InsituClient *c = NULL;
    if (insitu_connect(argc > 1 ? argv[1] : "127.0.0.1:1", NULL, &c) != INSITU_STATUS_OK) {
        printf("connect failed: %s\n", insitu_last_error());
        return 1;
    }
    uint32_t dims[3] = {16, 16, 16}, zero[3] = {0, 0, 0};
    size_t n = 16 * 16 * 16;
    float *field = calloc(n, sizeof(float));
    InsituStatus s = insitu_push_step(c, 1, 0.0, field, n * sizeof(float), INSITU_DTYPE_F64, dims,
                                      zero, dims, NULL, 0, 1, NULL);
    printf("short %d %s\n", (int)s, insitu_last_error());
    insitu_close(&c, 10.0, NULL);
    s = insitu_push_step(c, 2, 0.0, field, n * sizeof(float), INSITU_DTYPE_F32, dims, zero, dims,
                         NULL, 0, 1, NULL);
    printf("closed %d %s\n", (int)s, insitu_last_error());
    free(field);
    return 0;
}
