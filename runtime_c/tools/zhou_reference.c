/* The hand-written zhou MLP (see zhou_reference.h). Every line is one operation of the
 * exported graph, in its order, so rounding matches the runtime's step by step. */
#include "zhou_reference.h"

#include "kernels.h" /* pc_tanh_inline: the runtime's tanh */

#include <math.h>

static float norm_of(float n2)
{
    return sqrtf(n2 > 1e-24f ? n2 : 1e-24f);
}

/* One dense layer o = act(x W + b): each output sums bias, then x[k] W[k][n] in k order
 * (as the runtime does), with k outermost so the n loop vectorises. */
static void dense(const float *x, size_t k_in, const float *restrict w, const float *b,
                  size_t n_out, int tanh_act, float *restrict o)
{
    size_t n, k;
    for (n = 0; n < n_out; n++)
        o[n] = b[n];
    for (k = 0; k < k_in; k++)
        for (n = 0; n < n_out; n++)
            o[n] += x[k] * w[k * n_out + n];
    if (tanh_act)
        for (n = 0; n < n_out; n++)
            o[n] = pc_tanh_inline(o[n]);
}

static void quarter(float t, float a, float b, float c, int slot, float *q)
{
    const float m = t > 1e-12f ? t : 1e-12f;
    const float k = 1.0f / (sqrtf(m) * 2.0f);
    float v[3];
    v[0] = a * k;
    v[1] = b * k;
    v[2] = c * k;
    /* t * k goes into position slot, the three others fill the rest in order */
    q[0] = slot == 0 ? t * k : v[0];
    q[1] = slot == 1 ? t * k : slot == 0 ? v[0] : v[1];
    q[2] = slot == 2 ? t * k : slot < 2 ? v[1] : v[2];
    q[3] = slot == 3 ? t * k : v[2];
}

void pc_zhou_encode(const pc_zhou_weights *w, const float *in, float *x)
{
    float qw, qx, qy, qz, s, n2;
    int i;

    /* encode: unit quaternion -> first two columns of its matrix */
    n2 = 0.0f + in[3] * in[3] + in[4] * in[4] + in[5] * in[5] + in[6] * in[6];
    s = norm_of(n2);
    qw = in[3] / s;
    qx = in[4] / s;
    qy = in[5] / s;
    qz = in[6] / s;
    x[0] = in[0];
    x[1] = in[1];
    x[2] = in[2];
    x[3] = 1.0f - (qy * qy + qz * qz) * 2.0f;  /* m00 */
    x[4] = (qx * qy + qw * qz) * 2.0f;         /* m10 */
    x[5] = (qx * qz - qw * qy) * 2.0f;         /* m20 */
    x[6] = (qx * qy - qw * qz) * 2.0f;         /* m01 */
    x[7] = 1.0f - (qx * qx + qz * qz) * 2.0f;  /* m11 */
    x[8] = (qy * qz + qw * qx) * 2.0f;         /* m21 */
    for (i = 0; i < PC_ZHOU_IN; i++)
        x[i] = x[i] * w->in_scale[i] + w->in_offset[i];
}

void pc_zhou_network(const pc_zhou_weights *w, const float *x, float *y)
{
    float h[PC_ZHOU_HIDDEN], g[PC_ZHOU_HIDDEN];
    int i, l;

    dense(x, PC_ZHOU_IN, w->w_in, w->b_in, PC_ZHOU_HIDDEN, 1, h);
    for (l = 0; l < PC_ZHOU_LAYERS - 2; l++) {
        dense(h, PC_ZHOU_HIDDEN, w->w_hidden[l], w->b_hidden[l], PC_ZHOU_HIDDEN, 1, g);
        for (i = 0; i < PC_ZHOU_HIDDEN; i++)
            h[i] = g[i];
    }
    dense(h, PC_ZHOU_HIDDEN, w->w_out, w->b_out, PC_ZHOU_IN, 0, y);
}

void pc_zhou_decode(const pc_zhou_weights *w, const float *y_net, float *out)
{
    float y[PC_ZHOU_IN], s, e1[3], e2[3], u[3], d, n2;
    float r00, r01, r02, r10, r11, r12, r20, r21, r22;
    float t0, t1, t2, t3, qa[4], qb[4], qc[4], qd[4], q[4];
    const float *pick;
    int i;

    for (i = 0; i < PC_ZHOU_IN; i++)
        y[i] = y_net[i] * w->out_scale[i] + w->out_offset[i];

    /* decode: Gram-Schmidt on the two columns, their cross product the third */
    n2 = 0.0f + y[3] * y[3] + y[4] * y[4] + y[5] * y[5];
    s = norm_of(n2);
    for (i = 0; i < 3; i++)
        e1[i] = y[3 + i] / s;
    d = 0.0f + e1[0] * y[6] + e1[1] * y[7] + e1[2] * y[8];
    for (i = 0; i < 3; i++)
        u[i] = y[6 + i] - d * e1[i];
    n2 = 0.0f + u[0] * u[0] + u[1] * u[1] + u[2] * u[2];
    s = norm_of(n2);
    for (i = 0; i < 3; i++)
        e2[i] = u[i] / s;
    r00 = e1[0];
    r10 = e1[1];
    r20 = e1[2];
    r01 = e2[0];
    r11 = e2[1];
    r21 = e2[2];
    r02 = e1[1] * e2[2] - e1[2] * e2[1];
    r12 = e1[2] * e2[0] - e1[0] * e2[2];
    r22 = e1[0] * e2[1] - e1[1] * e2[0];

    /* matrix -> quaternion from the largest of the four diagonal combinations */
    t0 = r00 + 1.0f + r11 + r22;
    t1 = r00 + 1.0f - r11 - r22;
    t2 = 1.0f - r00 + r11 - r22;
    t3 = 1.0f - r00 - r11 + r22;
    quarter(t0, r21 - r12, r02 - r20, r10 - r01, 0, qa);
    quarter(t1, r21 - r12, r01 + r10, r02 + r20, 1, qb);
    quarter(t2, r02 - r20, r01 + r10, r12 + r21, 2, qc);
    quarter(t3, r10 - r01, r02 + r20, r12 + r21, 3, qd);
    pick = (t0 > t1 ? t0 : t1) >= (t2 > t3 ? t2 : t3) ? (t0 >= t1 ? qa : qb)
                                                      : (t2 >= t3 ? qc : qd);
    n2 = 0.0f + pick[0] * pick[0] + pick[1] * pick[1] + pick[2] * pick[2] + pick[3] * pick[3];
    s = norm_of(n2);
    for (i = 0; i < 4; i++)
        q[i] = pick[i] / s;
    if (q[0] < 0.0f)
        for (i = 0; i < 4; i++)
            q[i] = -q[i];
    out[0] = y[0];
    out[1] = y[1];
    out[2] = y[2];
    for (i = 0; i < 4; i++)
        out[3 + i] = q[i];
}

void pc_zhou_reference(const pc_zhou_weights *w, const float *in, float *out)
{
    float x[PC_ZHOU_IN], y[PC_ZHOU_IN];
    pc_zhou_encode(w, in, x);
    pc_zhou_network(w, x, y);
    pc_zhou_decode(w, y, out);
}
