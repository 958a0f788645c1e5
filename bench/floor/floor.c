/* floor.c MODEL: single-pose time of libposecorr's pc_run against a hand-written C function of
 * the same zhou MLP (written by gen_hand.py from the model: same weights, same
 * math), interleaved in rounds in one process. Public API only. A copy of the host floor's
 * harness (the floor script), used by bench/floor_all.py.
 * Prints: median ns per pose of each, their max abs output difference, and the ratio.
 * floor.c MODEL pc|hand: the poses once through one of them, nothing timed, for
 * valgrind --tool=callgrind --toggle-collect=run_pc (or run_hand): instructions a pose,
 * which a host shared with other work does not change. */
#define _POSIX_C_SOURCE 199309L
#include <posecorr.h>
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <time.h>
void hand_avx_correct(const float *in, float *out);
static double now_ns(void) { struct timespec t; clock_gettime(CLOCK_MONOTONIC, &t); return t.tv_sec * 1e9 + t.tv_nsec; }
static int cmp(const void *a, const void *b) { double x = *(const double *)a, y = *(const double *)b; return x < y ? -1 : x > y; }
__attribute__((noinline)) void run_pc(pc_model *m, const float *in, int n, float *o)
{ int i; for (i = 0; i < n; i++) pc_run(m, in + i * 7, 1, o); }
__attribute__((noinline)) void run_hand(const float *in, int n, float *o)
{ int i; for (i = 0; i < n; i++) hand_avx_correct(in + i * 7, o); }
int main(int argc, char **argv)
{
    enum { P = 1024, ROUNDS = 41, REPS = 20 };
    static float in[P * 7], o1[7], o2[7];
    double tp[ROUNDS], th[ROUNDS], diff = 0;
    unsigned long s = 12345; pc_model *m; pc_error e; int r, i, k;
    if (argc < 2 || pc_load_file(argv[1], NULL, &m, &e) != PC_OK) { fprintf(stderr, "load failed: %s\n", argc < 2 ? "usage" : e.message); return 2; }
    for (i = 0; i < P; i++) {
        double q[4], n = 0;
        for (k = 0; k < 7; k++) { double u; s = s * 6364136223846793005UL + 1442695040888963407UL; u = (double)((s >> 11) & 0xfffffffffffffUL) / 4503599627370496.0;
            if (k < 3) in[i * 7 + k] = (float)((k == 1 ? -0.6 : k == 2 ? 0.5 : 0.0) + 0.2 * u - 0.1); else q[k - 3] = 2 * u - 1; }
        for (k = 0; k < 4; k++) n += q[k] * q[k];
        for (k = 0; k < 4; k++) in[i * 7 + 3 + k] = (float)(q[k] / sqrt(n));
    }
    if (argc > 2) {
        if (argv[2][0] == 'p') run_pc(m, in, P, o1); else run_hand(in, P, o2);
        pc_free(m);
        return 0;
    }
    for (i = 0; i < P; i++) { pc_run(m, in + i * 7, 1, o1); hand_avx_correct(in + i * 7, o2);
        for (k = 0; k < 7; k++) if (fabs(o1[k] - o2[k]) > diff) diff = fabs(o1[k] - o2[k]); }
    for (r = 0; r < ROUNDS; r++) {
        double t0 = now_ns();
        for (k = 0; k < REPS; k++) for (i = 0; i < P; i++) pc_run(m, in + i * 7, 1, o1);
        double t1 = now_ns();
        for (k = 0; k < REPS; k++) for (i = 0; i < P; i++) hand_avx_correct(in + i * 7, o2);
        double t2 = now_ns();
        tp[r] = (t1 - t0) / (REPS * P); th[r] = (t2 - t1) / (REPS * P);
    }
    qsort(tp, ROUNDS, sizeof *tp, cmp); qsort(th, ROUNDS, sizeof *th, cmp);
    printf("pc_run %.1f ns, hand %.1f ns, max|diff| %.2g, ratio %.2f\n", tp[ROUNDS / 2], th[ROUNDS / 2], diff, tp[ROUNDS / 2] / th[ROUNDS / 2]);
    pc_free(m);
    return 0;
}
