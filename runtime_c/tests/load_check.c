/* Robustness driver for the sanitizer build: loads files (and, on request, every prefix,
 * random bit flips and random buffers derived from them), runs every model that loads,
 * and checks the pc_run contract on NaN input. Any memory error aborts under ASan/UBSan;
 * contract violations exit with status 1. */
#include "posecorr.h"

#include <math.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

/* xorshift64: 64-bit state on every host (unsigned long is 32 bits on a 32-bit one). */
static uint64_t rng_state = 88172645463325252ULL;
static uint64_t rnd(void)
{
    rng_state ^= rng_state << 13;
    rng_state ^= rng_state >> 7;
    rng_state ^= rng_state << 17;
    return rng_state;
}

static int failures = 0;
static unsigned long loaded = 0, attempts = 0;

static void exercise(pc_model *m)
{
    static float in[300 * 7], out[300 * 7];
    size_t i;
    for (i = 0; i < 300; i++) {
        in[i * 7 + 0] = 0.1f * (float)(i % 5);
        in[i * 7 + 1] = -0.2f;
        in[i * 7 + 2] = 0.3f;
        in[i * 7 + 3] = 1.0f;
        in[i * 7 + 4] = 0.0f;
        in[i * 7 + 5] = 0.0f;
        in[i * 7 + 6] = 0.0f;
    }
    (void)pc_run(m, in, 0, out);
    (void)pc_run(m, in, 1, out);
    (void)pc_run(m, in, 3, out);
    (void)pc_run(m, in, 300, out);
    /* NaN / inf: error, output untouched. */
    for (i = 0; i < 3 * 7; i++)
        out[i] = 12345.0f;
    in[2 * 7 + 4] = NAN;
    if (pc_run(m, in, 3, out) != PC_ERR_NONFINITE) {
        fprintf(stderr, "NaN input not rejected\n");
        failures++;
    }
    in[2 * 7 + 4] = INFINITY;
    if (pc_run(m, in, 3, out) != PC_ERR_NONFINITE) {
        fprintf(stderr, "inf input not rejected\n");
        failures++;
    }
    for (i = 0; i < 3 * 7; i++)
        if (out[i] != 12345.0f) {
            fprintf(stderr, "output touched on error\n");
            failures++;
            break;
        }
    if (pc_run(m, NULL, 1, out) != PC_ERR_ARGUMENT || pc_run(m, in, 1, NULL) != PC_ERR_ARGUMENT) {
        fprintf(stderr, "NULL buffers not rejected\n");
        failures++;
    }
}

static void try_load(const unsigned char *data, size_t size)
{
    /* the files here carry no digest or bounds, and a mutated one must reach the parser
     * rather than stop at its digest: loaded as another producer's */
    static const pc_options allow = {0, PC_LOAD_ALLOW_UNBOUNDED | PC_LOAD_ALLOW_UNSIGNED, 0};
    pc_model *m = NULL;
    pc_error err;
    pc_status st = pc_load_memory(data, size, &allow, &m, &err);
    attempts++;
    if (st == PC_OK) {
        loaded++;
        exercise(m);
        pc_free(m);
    } else if (m != NULL || err.message[0] == '\0' || st >= PC_STATUS_COUNT) {
        fprintf(stderr, "failed load left a model or no message (status %d)\n", (int)st);
        failures++;
    }
}

static unsigned char *read_file(const char *path, size_t *size)
{
    FILE *f = fopen(path, "rb");
    long n;
    unsigned char *buf;
    if (!f)
        return NULL;
    fseek(f, 0, SEEK_END);
    n = ftell(f);
    fseek(f, 0, SEEK_SET);
    buf = malloc(n > 0 ? (size_t)n : 1);
    if (buf && n > 0 && fread(buf, 1, (size_t)n, f) != (size_t)n) {
        free(buf);
        buf = NULL;
    }
    fclose(f);
    *size = (size_t)n;
    return buf;
}

int main(int argc, char **argv)
{
    int a, prefixes = 0;
    unsigned long flips = 0, randoms = 0, k;
    for (a = 1; a < argc; a++) {
        size_t size, i;
        unsigned char *data, *copy;
        if (strcmp(argv[a], "--prefixes") == 0) {
            prefixes = 1;
            continue;
        }
        if (strcmp(argv[a], "--flips") == 0 && a + 1 < argc) {
            flips = strtoul(argv[++a], NULL, 10);
            continue;
        }
        if (strcmp(argv[a], "--random") == 0 && a + 1 < argc) {
            randoms = strtoul(argv[++a], NULL, 10);
            continue;
        }
        data = read_file(argv[a], &size);
        if (!data) {
            fprintf(stderr, "cannot read %s\n", argv[a]);
            return 2;
        }
        try_load(data, size);
        copy = malloc(size + 1);
        if (!copy)
            return 2;
        if (prefixes)
            for (i = 0; i < size; i++) {
                /* A fresh heap copy of exactly i bytes, so ASan sees any over-read. */
                unsigned char *p = malloc(i ? i : 1);
                memcpy(p, data, i);
                try_load(p, i);
                free(p);
            }
        for (k = 0; k < flips && size; k++) {
            int nflip = 1 + (int)(rnd() % 3), j;
            memcpy(copy, data, size);
            for (j = 0; j < nflip; j++) {
                size_t pos = rnd() % size;
                if (rnd() % 4 == 0)
                    copy[pos] = (unsigned char)rnd();
                else
                    copy[pos] ^= (unsigned char)(1u << (rnd() % 8));
            }
            try_load(copy, size);
        }
        free(copy);
        free(data);
    }
    for (k = 0; k < randoms; k++) {
        size_t size = rnd() % 512, i;
        unsigned char *p = malloc(size ? size : 1);
        for (i = 0; i < size; i++)
            p[i] = (unsigned char)rnd();
        try_load(p, size);
        free(p);
    }
    printf("%lu loads attempted, %lu loaded, %d failures\n", attempts, loaded, failures);
    return failures ? 1 : 0;
}
