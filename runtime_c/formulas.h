/* Layer 4, kernels: the element formulas of libposecorr (Max and Min as ONNX has them,
 * ReLU, Clip, the logistic sigmoid, the library's tanh) and the list of the float element
 * operations with their expression in a and b. The kernels, the one-pose programs and the
 * dense layers compute with these (kernels.h includes this file), and `posecorr compile`
 * copies this file, as it is, into the C it writes, so that compiled code computes the same
 * bits. C99 and <math.h> only: nothing here may depend on the rest of the library. */
#ifndef PC_FORMULAS_H
#define PC_FORMULAS_H

#include <math.h>

/* A file that includes these uses some of them only; `posecorr compile` copies them into the
 * file it writes, where clang, unlike for a header's, warns of each one left unused. */
#if defined(__GNUC__)
#define PC_FORMULA static inline __attribute__((unused))
#else
#define PC_FORMULA static inline
#endif

/* Max/Min as ONNX has them: NaN from either side propagates. */
#define PC_MAX_EXPR(a, b) (((a) != (a) || (b) != (b)) ? (a) + (b) : (a) > (b) ? (a) : (b))
#define PC_MIN_EXPR(a, b) (((a) != (a) || (b) != (b)) ? (a) + (b) : (a) < (b) ? (a) : (b))

/* The hot float elementwise operators, X(kernel, element operation, expression of a and
 * b): one list makes the kernels (a table per layout for the binary ones, kernels.c) and
 * the one-pose programs' cases (k_scalar_program), so both compute the same formula. */
#define PC_RELU_EXPR(a) ((a) > 0.0f ? (a) : ((a) != (a) ? (a) : 0.0f))
#define PC_FLOAT_BINARY_OPS(X)                                                                 \
    X(k_add_f, PC_SOP_ADD, a + b)                                                              \
    X(k_sub_f, PC_SOP_SUB, a - b)                                                              \
    X(k_mul_f, PC_SOP_MUL, a * b)                                                              \
    X(k_div_f, PC_SOP_DIV, a / b)                                                              \
    X(k_max_f, PC_SOP_MAX, PC_MAX_EXPR(a, b))                                                  \
    X(k_min_f, PC_SOP_MIN, PC_MIN_EXPR(a, b))
#define PC_FLOAT_UNARY_OPS(X)                                                                  \
    X(k_abs_f, PC_SOP_ABS, fabsf(a))                                                           \
    X(k_neg_f, PC_SOP_NEG, -a)                                                                 \
    X(k_atan_f, PC_SOP_ATAN, atanf(a))                                                         \
    X(k_cos_f, PC_SOP_COS, cosf(a))                                                            \
    X(k_sin_f, PC_SOP_SIN, sinf(a))                                                            \
    X(k_tan_f, PC_SOP_TAN, tanf(a))                                                            \
    X(k_exp_f, PC_SOP_EXP, expf(a))                                                            \
    X(k_sqrt_f, PC_SOP_SQRT, sqrtf(a))                                                         \
    X(k_relu_f, PC_SOP_RELU, PC_RELU_EXPR(a))                                                  \
    X(k_sigmoid_f, PC_SOP_SIGMOID, pc_sigmoid(a))                                              \
    X(k_tanh_f, PC_SOP_TANH, pc_tanh_inline(a))

/* Clip as the dense layers fuse it: min(max(x, lo), hi). */
PC_FORMULA float pc_clip(float x, float lo, float hi)
{
    const float t = x < lo ? lo : x;
    return t > hi ? hi : t;
}

PC_FORMULA float pc_sigmoid(float x)
{
    return 1.0f / (1.0f + expf(-x));
}

/* The radial basis, as its three graph nodes compute it (Mul, Neg, Exp): the square is
 * rounded to float before the exponential, as their stored results are. */
PC_FORMULA float pc_radbas(float x)
{
    const float square = x * x;
    return expf(-square);
}

/* tanh(x) = x P(x^2) / Q(x^2) on |x| <= 9, +-1 beyond (tanh(9) = 1 - 3e-8). Coefficients
 * fitted for this library by iteratively reweighted least squares towards minimax
 * absolute error (5.9e-9 in exact arithmetic, 3.2e-7 evaluated in float32). Branch-free
 * so that loops over it vectorise; NaN propagates through the clamps. */
PC_FORMULA float pc_tanh_inline(float x)
{
    float c = x > 9.0f ? 9.0f : x;
    float t, p, q;
    c = c < -9.0f ? -9.0f : c;
    t = c * c;
    p = -8.291313e-14f;
    p = p * t + 5.1926935e-11f;
    p = p * t + -2.0029567e-08f;
    p = p * t + 1.1101826e-05f;
    p = p * t + 0.0030986548f;
    p = p * t + 0.13079165f;
    p = p * t + 0.99999994f;
    q = 0.00025386017f;
    q = q * t + 0.024473764f;
    q = q * t + 0.46412486f;
    q = q * t + 1.0f;
    p = c * p / q;
    /* |tanh| <= 1 must hold exactly: callers may feed it to acos-like maths. */
    p = p > 1.0f ? 1.0f : p;
    return p < -1.0f ? -1.0f : p;
}

/* ---- pc_run's contract on a pose (run.c), which the functions `posecorr compile` writes
 * check the same way, with the same numbers ---- */

/* An input quaternion's norm may be off 1 by 1e-3 (posecorr.h). The model normalises what
 * it is given, so a few lost bits change nothing; the tolerance is the one of the pose
 * tables (python/posecorr/data.py) and posecorr-run, so that a pose they accept is accepted
 * here. A float32 unit quaternion is within 1e-7 of norm 1, one printed with four decimals
 * within 2e-4: both pass. A zero, a norm-3 or a garbled vector is a glitch, not an
 * orientation, and normalising it would answer with a made-up rotation. Compared on |q|^2
 * in double: (1 -+ 1e-3)^2. */
#define PC_QUAT_NORM2_LO 0.998001
#define PC_QUAT_NORM2_HI 1.002001
/* |q|^2 summed in float, in any order, is within 3e-7 (relative) of the exact sum: one
 * within this of 1 is inside [LO, HI] in double for certain (0.00199 + 3e-7 < 0.001999).
 * pc_run sums in double only outside it: a pose it refuses, or one within 1e-5 of the
 * tolerance (a Cortex-M4's FPU has no double). */
#define PC_QUAT_NORM2_BAND 0.00199f
/* |q|^2 of a float32 unit quaternion after a few dozen operations is within 1e-5 of 1, and
 * a broken graph's is far off. The output is held to the input's rule, (1 + 1e-3)^2 - 1 =
 * 2.001e-3 with float slack: a position-only model passes the input's quaternion through,
 * so a pose pc_run accepts must not come out refused as the model's failure. */
#define PC_UNIT_TOLERANCE 2.002e-3f

/* |q|^2 of an input quaternion q[4], in double. The tests below join their clauses with &,
 * not &&: pc_run's hot check takes no branch per clause. */
PC_FORMULA double pc_input_norm2(const float *q)
{
    return (double)q[0] * q[0] + (double)q[1] * q[1] + (double)q[2] * q[2] + (double)q[3] * q[3];
}

PC_FORMULA int pc_unit_input(double norm2)
{
    return (norm2 >= PC_QUAT_NORM2_LO) & (norm2 <= PC_QUAT_NORM2_HI);
}

/* pc_unit_input of q[4] given norm2_float, its |q|^2 summed in float in any order: the sum
 * in double only outside PC_QUAT_NORM2_BAND, where the float one cannot decide. */
PC_FORMULA int pc_unit_input_banded(float norm2_float, const float *q)
{
    if (fabsf(norm2_float - 1.0f) <= PC_QUAT_NORM2_BAND)
        return 1;
    return pc_unit_input(pc_input_norm2(q));
}

/* How the output pose p[7] moved from the input pose in[7]: |p_out - p_in|^2, |q_out|^2,
 * q_in . q_out and |q_in|^2, each summed in column order. */
typedef struct pc_move {
    float d2, n2, dot, n_in2;
} pc_move;

PC_FORMULA pc_move pc_move_of(const float *in, const float *p)
{
    pc_move v = {0.0f, 0.0f, 0.0f, 0.0f};
    int c;
    for (c = 0; c < 3; c++) {
        const float d = p[c] - in[c];
        v.d2 += d * d;
    }
    for (c = 3; c < 7; c++) {
        v.n2 += p[c] * p[c];
        v.dot += p[c] * in[c];
        v.n_in2 += in[c] * in[c];
    }
    return v;
}

PC_FORMULA int pc_unit_output(const pc_move *v)
{
    return fabsf(v->n2 - 1.0f) <= PC_UNIT_TOLERANCE;
}

/* Within the model's reach, compared on squares: |p_out - p_in|^2 against reach_pos2, and
 * (q_in . q_out)^2 against cos^2(reach / 2) |q_in|^2 |q_out|^2 (reach_cos2 0: any rotation),
 * a few multiplications a pose. */
PC_FORMULA int pc_within_reach(const pc_move *v, float reach_pos2, float reach_cos2)
{
    return (v->d2 <= reach_pos2) & (v->dot * v->dot >= reach_cos2 * v->n_in2 * v->n2);
}

#endif
