/* Built against an installed client (client-c/install.sh) through pkg-config and through CMake
 * by tests/tests/e2e/install.rs: connects to ADDR (nothing listens there) and expects
 * INSITU_STATUS_UNREACHABLE with a message, then closes the null handle. */
#include <stdio.h>
#include "insitu.h"
int main(int argc, char **argv) {
    InsituClient *c = NULL;
    InsituStatus s = insitu_connect(argc > 1 ? argv[1] : "127.0.0.1:1", NULL, &c);
    printf("connect %d %s\n", (int)s, insitu_last_error());
    insitu_close(&c, 1.0, NULL);
    return s == INSITU_STATUS_UNREACHABLE ? 0 : 1;
}
