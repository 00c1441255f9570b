/* Runs the fused kernel's dk_fk on one call dumped by benchmarks/native_profile.py, outside Python, so that
 * valgrind --tool=callgrind counts the kernel's instructions alone (and quickly: no interpreter under the
 * emulator) and the wall clock sees no ctypes overhead.
 *
 *     native_driver LIBRARY DUMP REPS
 *
 * DUMP: int64 struct size, the struct's bytes (native.Args, filled), int64 count, then per pointer field
 * int64 offset, int64 bytes, the bytes. The driver knows nothing of the layout: it copies the arrays and
 * patches their addresses in at the offsets given. Prints the best and the median seconds of REPS calls. */
#include <dlfcn.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>

static int64_t read_i64(FILE *f) {
    int64_t v = 0;
    if (fread(&v, sizeof v, 1, f) != 1) { fprintf(stderr, "truncated dump\n"); exit(2); }
    return v;
}

static int cmp(const void *a, const void *b) {
    const double x = *(const double *)a, y = *(const double *)b;
    return (x > y) - (x < y);
}

int main(int argc, char **argv) {
    if (argc != 4) { fprintf(stderr, "usage: %s LIBRARY DUMP REPS\n", argv[0]); return 2; }
    void *lib = dlopen(argv[1], RTLD_NOW);
    if (!lib) { fprintf(stderr, "%s\n", dlerror()); return 2; }
    int64_t (*fk)(const void *) = (int64_t (*)(const void *))dlsym(lib, "dk_fk");
    FILE *f = fopen(argv[2], "rb");
    if (!fk || !f) { fprintf(stderr, "no dk_fk or no dump\n"); return 2; }
    const int64_t size = read_i64(f);
    char *args = malloc((size_t)size);
    if (fread(args, 1, (size_t)size, f) != (size_t)size) { fprintf(stderr, "truncated dump\n"); return 2; }
    for (int64_t i = 0, count = read_i64(f); i < count; i++) {
        const int64_t off = read_i64(f), bytes = read_i64(f);
        void *p = aligned_alloc(64, ((size_t)bytes + 63) / 64 * 64);
        if (fread(p, 1, (size_t)bytes, f) != (size_t)bytes) { fprintf(stderr, "truncated dump\n"); return 2; }
        memcpy(args + off, &p, sizeof p);
    }
    fclose(f);
    const int reps = atoi(argv[3]);
    double *t = malloc(sizeof(double) * (size_t)(reps > 0 ? reps : 1));
    int64_t status = 0;
    for (int r = 0; r < reps; r++) {
        struct timespec t0, t1;
        clock_gettime(CLOCK_MONOTONIC, &t0);
        status |= fk(args);
        clock_gettime(CLOCK_MONOTONIC, &t1);
        t[r] = (double)(t1.tv_sec - t0.tv_sec) + 1e-9 * (double)(t1.tv_nsec - t0.tv_nsec);
    }
    qsort(t, (size_t)reps, sizeof(double), cmp);
    printf("status %lld best %.9f median %.9f\n", (long long)status, reps ? t[0] : 0.0, reps ? t[reps / 2] : 0.0);
    return status != 0;
}
