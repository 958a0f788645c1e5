/* once.c MODEL pc|hand: 1,000 poses once through pc_run or through the hand-written function
 * (gen_hand.py), for valgrind --tool=callgrind --toggle-collect=run_pc (or run_hand):
 * instructions a pose, which a host shared with other work does not change. Same poses as
 * floor.c. */
#include <posecorr.h>
#include <math.h>
#include <stdio.h>
#include <string.h>
void hand_avx_correct(const float *in, float *out);
__attribute__((noinline)) void run_pc(pc_model *m, const float *in, int n, float *o)
{
    int i;
    for (i = 0; i < n; i++)
        pc_run(m, in + i * 7, 1, o);
}
__attribute__((noinline)) void run_hand(const float *in, int n, float *o)
{
    int i;
    for (i = 0; i < n; i++)
        hand_avx_correct(in + i * 7, o);
}
int main(int argc, char **argv)
{
    enum { P = 1000 };
    static float in[P * 7], o[7];
    unsigned long s = 12345;
    pc_model *m;
    pc_error e;
    int i, k;
    if (argc < 3 || pc_load_file(argv[1], NULL, &m, &e) != PC_OK) {
        fprintf(stderr, "usage: once MODEL pc|hand (or the model does not load)\n");
        return 2;
    }
    for (i = 0; i < P; i++) {
        double q[4], n = 0;
        for (k = 0; k < 7; k++) {
            double u;
            s = s * 6364136223846793005UL + 1442695040888963407UL;
            u = (double)((s >> 11) & 0xfffffffffffffUL) / 4503599627370496.0;
            if (k < 3)
                in[i * 7 + k] = (float)((k == 1 ? -0.6 : k == 2 ? 0.5 : 0.0) + 0.2 * u - 0.1);
            else
                q[k - 3] = 2 * u - 1;
        }
        for (k = 0; k < 4; k++)
            n += q[k] * q[k];
        for (k = 0; k < 4; k++)
            in[i * 7 + 3 + k] = (float)(q[k] / sqrt(n));
    }
    if (strcmp(argv[2], "pc") == 0)
        run_pc(m, in, P, o);
    else
        run_hand(in, P, o);
    pc_free(m);
    return 0;
}
