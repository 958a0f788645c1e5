/* pc_run: validate, then walk the precomputed plans. n is split greedily into chunks of
 * the planned batch sizes (max_batch, ..., 256, 16, 1) so every chunk runs a plan whose
 * shapes, pointers and kernels were fixed at load; each chunk's result is checked
 * before it is copied out. */
#include "model.h"

#include <float.h>
#include <math.h>
#include <string.h>

/* The contract's numbers and tests (PC_QUAT_NORM2_LO/HI, PC_UNIT_TOLERANCE, pc_move_of,
 * pc_within_reach) are formulas.h's, which `posecorr compile` copies into its functions. */
#include "formulas.h"

/* The failing step of a plan, as the message. */
PC_RARE static pc_status pc_step_failed(pc_model *m, const pc_plan *plan, const pc_step *s,
                                        pc_status st)
{
    pc_format(m->message, sizeof m->message, "step %zu of the N=%zu plan failed: %s",
              (size_t)(s - plan->steps), plan->batch, pc_status_name(st));
    return st;
}

PC_HOT pc_status pc_run_steps(pc_model *m, const pc_plan *plan)
{
    const pc_step *s = plan->steps;
    const pc_step *const end = s + plan->n_steps;
    for (; s < end; s++) {
        const pc_status st = s->fn(s);
        if (st != PC_OK)
            return pc_step_failed(m, plan, s, st);
    }
    return PC_OK;
}

PC_RARE static void pc_decimal(char *buf, size_t size, double v, int places);

/* The contract's names of a pose's columns, in and out (posecorr.h): a message names a
 * column by them, where an index ("column 1") read as the first or as the second. */
static const char pc_column_names[PC_POSE_WIDTH][3] = {"x", "y", "z", "qw", "qx", "qy", "qz"};

/* "...moves the pose by D m and A rad, beyond ..." of a pose moved farther than the
 * model's correction_reach (python/posecorr/controller/checks.py writes the same). */
PC_RARE static void pc_beyond_reach(pc_model *m, size_t pose, float d2, float dot, float n_in2,
                                    float n_out2)
{
    char dist[24], angle[24], reach_pos[24], reach_rot[24];
    double c = fabs((double)dot) / sqrt((double)n_in2 * (double)n_out2);
    pc_decimal(dist, sizeof dist, sqrt((double)d2), 3);
    pc_decimal(angle, sizeof angle, 2.0 * acos(c < 1.0 ? c : 1.0), 3);
    pc_decimal(reach_pos, sizeof reach_pos, sqrt((double)m->reach_pos2), 3);
    pc_decimal(reach_rot, sizeof reach_rot, 2.0 * acos(sqrt((double)m->reach_cos2)), 3);
    pc_format(m->message, sizeof m->message,
              "pose %zu: output 'corrected' moves the pose by %s m and %s rad, beyond the "
              "model's reach of %s m and %s rad (metadata correction_reach)", pose, dist,
              angle, reach_pos, reach_rot);
}

/* Whether the seven values of a pose are all finite and its position inside [lo, hi], with
 * no branch per value: the checks' common case in a few instructions (SSE2 on x86-64:
 * x - x is NaN exactly for an infinity or a NaN; the loads of lanes 0-3 and 3-6 stay
 * inside the pose, those of lo and hi inside the model). A PC_NO_AVX2 build runs the
 * portable form, which the tests compare with this one. */
#if defined(__SSE2__) && !defined(PC_NO_AVX2)
#include <emmintrin.h>
PC_HOT static int pc_pose_finite(const float *v)
{
    const __m128 a = _mm_loadu_ps(v), b = _mm_loadu_ps(v + 3);
    const __m128 da = _mm_sub_ps(a, a), db = _mm_sub_ps(b, b);
    return _mm_movemask_ps(_mm_and_ps(_mm_cmpord_ps(da, da), _mm_cmpord_ps(db, db))) == 15;
}

PC_HOT static int pc_pose_in_box(const pc_model *m, const float *v)
{
    const __m128 p = _mm_loadu_ps(v);
    const __m128 in = _mm_and_ps(_mm_cmpge_ps(p, _mm_loadu_ps(m->lo)),
                                 _mm_cmple_ps(p, _mm_loadu_ps(m->hi)));
    return (_mm_movemask_ps(in) & 7) == 7;
}

/* |q|^2 of an input quaternion in float, in the lanes' order (PC_QUAT_NORM2_BAND). */
PC_HOT static float pc_norm2_float(const float *q)
{
    const __m128 v = _mm_loadu_ps(q);
    const __m128 sq = _mm_mul_ps(v, v);
    const __m128 half = _mm_add_ps(sq, _mm_movehl_ps(sq, sq));
    return _mm_cvtss_f32(_mm_add_ss(half, _mm_shuffle_ps(half, half, 1)));
}

/* A pose's seven floats between the caller's buffer and the arena, as two overlapping
 * groups of four. */
PC_HOT static void pc_pose_copy(float *to, const float *from)
{
    const __m128 a = _mm_loadu_ps(from), b = _mm_loadu_ps(from + 3);
    _mm_storeu_ps(to, a);
    _mm_storeu_ps(to + 3, b);
}

#else
PC_HOT static int pc_pose_finite(const float *v)
{
    uint32_t bad = 0, bits;
    size_t i;
    for (i = 0; i < PC_POSE_WIDTH; i++) {
        memcpy(&bits, v + i, sizeof bits);
        bad |= (uint32_t)((bits & 0x7f800000u) == 0x7f800000u);
    }
    return !bad;
}

PC_HOT static int pc_pose_in_box(const pc_model *m, const float *v)
{
    return (v[0] >= m->lo[0]) & (v[0] <= m->hi[0]) & (v[1] >= m->lo[1]) &
           (v[1] <= m->hi[1]) & (v[2] >= m->lo[2]) & (v[2] <= m->hi[2]);
}

PC_HOT static float pc_norm2_float(const float *q)
{
    return ((q[0] * q[0] + q[1] * q[1]) + q[2] * q[2]) + q[3] * q[3];
}

PC_HOT static void pc_pose_copy(float *to, const float *from)
{
    size_t i;
    for (i = 0; i < PC_POSE_WIDTH; i++)
        to[i] = from[i];
}

#endif

/* The output contract: finite, a unit quaternion, and a correction (from the input in)
 * within the model's reach (formulas.h: pc_move_of, pc_unit_output, pc_within_reach); the
 * finite test only where the reach does not imply it (m->bounded). GCC reads the decoder's
 * results (stored one float at a time) with wider loads here; reading them one float at a
 * time measured slower on the EPYC (zhou 5: +1.5 to +6 ns a pose), so it is left so. */
PC_INLINE int pc_output_ok(const pc_model *m, const float *in, const float *p)
{
    const pc_move v = pc_move_of(in, p);
    const int ok = pc_unit_output(&v) & pc_within_reach(&v, m->reach_pos2, m->reach_cos2);
    return m->bounded ? ok : ok & pc_pose_finite(p);
}

/* The first column of a pose that is not finite; PC_POSE_WIDTH when every one is. */
PC_RARE static size_t pc_first_nonfinite(const float *v)
{
    size_t c = 0;
    while (c < PC_POSE_WIDTH && isfinite(v[c]))
        c++;
    return c;
}

/* The clause of the contract that pose `pose`'s output p breaks, as the message. */
PC_RARE static pc_status pc_output_error(pc_model *m, const float *in, const float *p,
                                         size_t pose)
{
    const pc_move v = pc_move_of(in, p);
    const size_t c = pc_first_nonfinite(p);
    if (c < PC_POSE_WIDTH) {
        pc_format(m->message, sizeof m->message, "pose %zu: %s of output 'corrected' is not "
                  "finite (expected a finite number)", pose, pc_column_names[c]);
        return PC_ERR_RUNTIME;
    }
    if (!pc_unit_output(&v)) {
        pc_format(m->message, sizeof m->message, "pose %zu: the quaternion qw, qx, qy, qz of "
                  "output 'corrected' is not unit (expected |q|^2 within 0.002 of 1)", pose);
        return PC_ERR_RUNTIME;
    }
    pc_beyond_reach(m, pose, v.d2, v.dot, v.n_in2, v.n2);
    return PC_ERR_RUNTIME;
}

/* Each clause evaluated without a branch; a pose that fails one is reported by
 * pc_output_error, which finds the first. */
PC_HOT static pc_status pc_check_output(pc_model *m, const float *in, const float *out, size_t n,
                                        size_t first)
{
    size_t r;
    for (r = 0; r < n; r++, in += PC_POSE_WIDTH, out += PC_POSE_WIDTH)
        if (!pc_output_ok(m, in, out))
            return pc_output_error(m, in, out, first + r);
    return PC_OK;
}

/* The network on one pose, through the plan of batch 1 (t NULL: t = 0). */
PC_INLINE pc_status pc_pose_steps(pc_model *m, const pc_plan *plan, const float *in,
                                  const float *t)
{
    pc_pose_copy(plan->in, in);
    if (plan->t)
        plan->t[0] = t ? t[0] : 0.0f;
    return pc_run_steps(m, plan);
}

/* The output check of the pose the plan of batch 1 ran (pose `index` of the call, for the
 * message), then its copy out. */
PC_INLINE pc_status pc_pose_out(pc_model *m, const pc_plan *plan, const float *in, float *out,
                                size_t index)
{
    if (!pc_output_ok(m, in, plan->out))
        return pc_output_error(m, in, plan->out, index);
    pc_pose_copy(out, plan->out);
    return PC_OK;
}

/* One pose through the plan of batch 1, its input already checked. */
PC_INLINE pc_status pc_run_pose(pc_model *m, const float *in, const float *t, float *out,
                                size_t index)
{
    const pc_plan *plan = &m->plans[0];
    const pc_status st = pc_pose_steps(m, plan, in, t);
    return st != PC_OK ? st : pc_pose_out(m, plan, in, out, index);
}

/* t NULL: every pose at t = 0. */
static pc_status pc_run_plan(pc_model *m, const pc_plan *plan, const float *in, const float *t,
                             float *out, size_t first)
{
    const size_t count = plan->batch * PC_POSE_WIDTH;
    pc_status st;
    if (plan->batch == 1)
        return pc_run_pose(m, in, t, out, first);
    memcpy(plan->in, in, count * sizeof(float));
    if (plan->t) {
        if (t)
            memcpy(plan->t, t, plan->batch * sizeof(float));
        else
            memset(plan->t, 0, plan->batch * sizeof(float));
    }
    if ((st = pc_run_steps(m, plan)) != PC_OK ||
        (st = pc_check_output(m, in, plan->out, plan->batch, first)) != PC_OK)
        return st;
    /* the caller's out never overlaps the arena */
    memcpy(out, plan->out, count * sizeof(float));
    return PC_OK;
}

/* v with `places` decimals (at most 6) for a message, from 1e9 on as a mantissa and a
 * power of ten (3.000e30), inf and nan as such: pc_format has no %f or %e. The rule is
 * python/posecorr/controller/checks.py's decimal(), step for step in the same doubles, so
 * that both back ends write the same text. */
PC_RARE static void pc_decimal(char *buf, size_t size, double v, int places)
{
    char frac[8], power[8] = "";
    const int scientific = fabs(v) >= 1e9;
    double a = fabs(v), decade = 1e9, scale = 1.0;
    long long units, f;
    int k, exponent = 9;
    if (!(a <= DBL_MAX)) { /* a reach or distance may be infinite, or nan */
        pc_format(buf, size, "%s", a != a ? "nan" : v < 0 ? "-inf" : "inf");
        return;
    }
    if (scientific) {
        while (a >= decade * 10.0) {
            decade *= 10.0;
            exponent++;
        }
        a /= decade;
    }
    for (k = 0; k < places; k++)
        scale *= 10.0;
    units = (long long)(a * scale + 0.5);
    if (scientific) {
        if (units >= 10 * (long long)scale) { /* 9.9996e12 rounds to 1.000e13 */
            units /= 10;
            exponent++;
        }
        pc_format(power, sizeof power, "e%d", exponent);
    }
    for (k = places, f = units; k > 0; k--, f /= 10)
        frac[k - 1] = (char)('0' + f % 10);
    frac[places] = '\0';
    pc_format(buf, size, "%s%lld.%s%s", v < 0 && units ? "-" : "", units / (long long)scale,
              frac, power);
}

/* What pc_outside says is outside: a position, a time the caller gave, or the t = 0 of a
 * call without times. */
enum { PC_POSITION, PC_TIME, PC_NO_TIME };

/* "pose I: NAME = VALUE UNIT is outside the range the model was fitted on, LO to HI UNIT
 * (metadata input_bounds)" of a position outside the box, or of a time (NAME t) outside
 * the span; of a call without times, that its poses were taken at t = 0. */
PC_RARE static void pc_outside(pc_model *m, size_t pose, const char *name, float v, float lo,
                               float hi, int what)
{
    char value[24], low[24], high[24];
    const char *unit = what == PC_POSITION ? "m" : "s";
    pc_decimal(value, sizeof value, v, 3);
    pc_decimal(low, sizeof low, lo, 3);
    pc_decimal(high, sizeof high, hi, 3);
    if (what == PC_NO_TIME)
        pc_format(m->message, sizeof m->message, "pose %zu: no t given, so t = 0 s, outside the "
                  "span the model was fitted on, %s to %s s (metadata time_bounds): the model "
                  "takes each pose's time", pose, low, high);
    else
        pc_format(m->message, sizeof m->message, "pose %zu: %s = %s %s is outside the %s the model "
                  "was fitted on, %s to %s %s (metadata %s)", pose, name, value, unit,
                  what == PC_TIME ? "span" : "range", low, high, unit,
                  what == PC_TIME ? "time_bounds" : "input_bounds");
}

/* Whether a pose meets the input contract, the clauses joined without a branch; the finite
 * test only where the box does not imply it (m->bounded: a quaternion of unit norm is
 * finite too), a branch on a constant of the model. */
PC_INLINE int pc_pose_ok(const pc_model *m, const float *in)
{
    const int ok = pc_pose_in_box(m, in) & pc_unit_input_banded(pc_norm2_float(in + 3), in + 3);
    return m->bounded ? ok : ok & pc_pose_finite(in);
}

/* The first clause of the input contract that pose i breaks, as the message: a value not
 * finite, then the quaternion (SteamVR's "no pose" is all zeros, its position too: that is
 * a zero quaternion, not a position outside the box), then the position. */
PC_RARE static pc_status pc_pose_error(pc_model *m, const float *in, size_t i)
{
    char norm[24];
    const double n2 = pc_input_norm2(in + 3);
    size_t c = pc_first_nonfinite(in);
    if (c < PC_POSE_WIDTH) {
        pc_format(m->message, sizeof m->message, "pose %zu: %s is not finite (expected a "
                  "finite number)", i, pc_column_names[c]);
        return PC_ERR_NONFINITE;
    }
    if (!pc_unit_input(n2)) { /* pc_unit_input_banded's answer, without its float shortcut */
        pc_decimal(norm, sizeof norm, sqrt(n2), 6);
        pc_format(m->message, sizeof m->message, "pose %zu: the quaternion qw, qx, qy, qz has "
                  "norm %s (expected a unit quaternion: norm within 0.001 of 1)", i, norm);
        return PC_ERR_QUATERNION;
    }
    for (c = 0; c < 2 && in[c] >= m->lo[c] && in[c] <= m->hi[c]; c++)
        ;
    pc_outside(m, i, pc_column_names[c], in[c], m->lo[c], m->hi[c], PC_POSITION);
    return PC_ERR_RANGE;
}

/* The time of a pose (t NULL: 0) meets the input contract: finite, and inside the fitted
 * span when the model records one (a constant of the model: the branch is predicted). */
PC_INLINE int pc_time_ok(const pc_model *m, const float *t)
{
    const float v = t ? *t : 0.0f;
    if (!m->has_span)
        return !t || isfinite(v);
    return (v >= m->t_lo) & (v <= m->t_hi); /* the bounds are finite */
}

/* The clause of the input contract that the time of pose i breaks, as the message; a call
 * without times (given 0) is told that its poses were taken at t = 0. */
PC_RARE static pc_status pc_time_error(pc_model *m, float ti, size_t i, int given)
{
    if (!isfinite(ti)) {
        pc_format(m->message, sizeof m->message, "pose %zu: t is not finite (expected seconds "
                  "since the session's start)", i);
        return PC_ERR_NONFINITE;
    }
    pc_outside(m, i, "t", ti, m->t_lo, m->t_hi, given ? PC_TIME : PC_NO_TIME);
    return PC_ERR_RANGE;
}

/* The input contract, pose by pose (python/posecorr/controller/checks.py checks the same
 * in the same order): finite times inside the fitted span (when the model records one;
 * no t is t = 0), then finite poses, unit quaternions and positions inside the training
 * box (input_bounds). */
PC_NOINLINE static pc_status pc_check_input(pc_model *m, const float *in, const float *t,
                                            size_t n)
{
    size_t i;
    const size_t n_times = t ? n : m->has_span ? 1 : 0;
    for (i = 0; i < n_times; i++)
        if (!pc_time_ok(m, t ? t + i : NULL))
            return pc_time_error(m, t ? t[i] : 0.0f, i, t != NULL);
    for (i = 0; i < n; i++, in += PC_POSE_WIDTH)
        if (!pc_pose_ok(m, in))
            return pc_pose_error(m, in, i);
    return PC_OK;
}

/* Whether pc_run of one pose runs the network before it checks the input. On an
 * out-of-order core it does: the steps only write the arena, a refused pose's result never
 * reaches out, and the encoder's first chain (|q|, its square root, the divisions) then
 * starts without the check's instructions ahead of it, so it overlaps more of the previous
 * call's last results (x86-64, an EPYC, the old and new library alternating in one process:
 * zhou 5 107 -> 104 ns a pose, zhou 10 111 -> 108, 10-10-10 168 -> 165). An in-order core
 * (the Cortex-M4) gains nothing and would keep in, t and out across the steps: 4
 * instructions a pose more. */
#if defined(__x86_64__) || defined(_M_X64)
#define PC_STEPS_FIRST 1
#else
#define PC_STEPS_FIRST 0
#endif

/* pc_run of one pose (model, in and out not NULL): the control loop's call, its contract
 * checked on values already in registers; a pose that breaks it gets pc_check_input's
 * message. */
PC_INLINE pc_status pc_run_one(pc_model *m, const float *in, const float *t, float *out)
{
#if PC_STEPS_FIRST
    const pc_plan *plan = &m->plans[0];
    pc_status st;
    m->message[0] = '\0'; /* before the steps: a failing one writes it */
    st = pc_pose_steps(m, plan, in, t);
    if (!(pc_time_ok(m, t) & pc_pose_ok(m, in)))
        return pc_check_input(m, in, t, 1);
    return st != PC_OK ? st : pc_pose_out(m, plan, in, out, 0);
#else
    if (!(pc_time_ok(m, t) & pc_pose_ok(m, in)))
        return pc_check_input(m, in, t, 1);
    m->message[0] = '\0';
    return pc_run_pose(m, in, t, out, 0);
#endif
}

/* Whether two buffers of `bytes` bytes overlap without being the same (the addresses as
 * integers: comparing pointers into different objects is undefined). */
static int pc_partly_overlap(const float *in, const float *out, size_t bytes)
{
    const uintptr_t a = (uintptr_t)in, b = (uintptr_t)out;
    return a != b && a < b + bytes && b < a + bytes;
}

/* Any n: the arguments checked, the input whole, then chunks of the planned sizes. */
PC_NOINLINE static pc_status pc_run_chunks(pc_model *model, const float *in, const float *t,
                                           size_t n, float *out)
{
    size_t k, done = 0;
    pc_status st;
    if (!model)
        return PC_ERR_ARGUMENT;
    model->message[0] = '\0';
    if (n == 0)
        return PC_OK;
    if (!in || !out) {
        pc_format(model->message, sizeof model->message, "pc_run: NULL %s buffer",
                  in ? "output" : "input");
        return PC_ERR_ARGUMENT;
    }
    if (n > ((size_t)-1) / (PC_POSE_WIDTH * sizeof(float))) {
        pc_format(model->message, sizeof model->message, "pc_run: n = %zu is too large", n);
        return PC_ERR_ARGUMENT;
    }
    /* Chunk k's output would overwrite a later chunk's input (one pose reads all of its
     * input before it writes, so pc_run_one needs no such check). */
    if (pc_partly_overlap(in, out, n * PC_POSE_WIDTH * sizeof(float))) {
        pc_format(model->message, sizeof model->message, "pc_run: out overlaps in without being "
                  "it (give the same array, or two that do not overlap)");
        return PC_ERR_ARGUMENT;
    }
    /* Reject before writing anything, so that out is untouched on these errors. */
    if ((st = pc_check_input(model, in, t, n)) != PC_OK)
        return st;
    while (done < n) {
        const size_t left = n - done;
        for (k = model->n_plans - 1; model->plans[k].batch > left; k--)
            ;
        st = pc_run_plan(model, &model->plans[k], in + done * PC_POSE_WIDTH,
                         t ? t + done : NULL, out + done * PC_POSE_WIDTH, done);
        if (st != PC_OK)
            return st;
        done += model->plans[k].batch;
    }
    return PC_OK;
}

/* pc_run and pc_run_timed, each one function on the one-pose path. */
PC_INLINE pc_status pc_run_poses(pc_model *model, const float *in, const float *t, size_t n,
                                 float *out)
{
    if (n == 1 && model && in && out)
        return pc_run_one(model, in, t, out);
    return pc_run_chunks(model, in, t, n, out);
}

PC_HOT pc_status pc_run(pc_model *model, const float *in, size_t n, float *out)
{
    return pc_run_poses(model, in, NULL, n, out);
}

PC_HOT pc_status pc_run_timed(pc_model *model, const float *in, const float *t, size_t n,
                              float *out)
{
    /* a model without the input t ignores it: its times are not checked either */
    return pc_run_poses(model, in, model && model->takes_time ? t : NULL, n, out);
}
