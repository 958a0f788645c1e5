/* The public load entry points and accessors. Every load runs pc_load_impl: scan the
 * graph (graph.c), plan (plan.c), then the checks that need a built model: rows must be
 * independent, and the metadata the pose checks of pc_run use. */
#include "graph.h"
#include "load.h"
#include "plan.h"

#include <float.h>
#include <math.h>
#include <stdlib.h>
#include <string.h>


/* ---- load-time checks ------------------------------------------------------------- */

/* Close enough for results of the same arithmetic in a different plan. Equal infinities
 * are the same result (their difference is NaN): a model answering a probe with infinity
 * is pc_run's output check to refuse, not a graph that mixes rows. */
static int pc_same_result(float a, float b)
{
    const float d = a > b ? a - b : b - a, s = a < 0 ? -a : a;
    return a == b || (a != a && b != b) || d <= 1e-5f * (s > 1.0f ? s : 1.0f);
}

static pc_status pc_forget_probe(pc_model *m)
{
    m->message[0] = '\0';
    return PC_OK;
}

/* pc_run splits a batch into chunks, so row i of the result must not depend on row j:
 * every pose of a batch plan must give what it gives alone. Checked on probe poses
 * (a reduction, reshape or gather across the batch axis fails it). */
PC_NOINLINE static pc_status pc_check_rows(pc_model *m, pc_error *err)
{
    float in[PC_PLAN_STRIDE * PC_POSE_WIDTH], out[PC_PLAN_STRIDE * PC_POSE_WIDTH];
    float t[PC_PLAN_STRIDE];
    const pc_plan *one = &m->plans[0], *batch;
    uint32_t seed = 12345u;
    size_t i, r, c;
    if (m->n_plans < 2)
        return PC_OK;
    batch = &m->plans[1];
    for (r = 0; r < batch->batch; r++) {
        float *p = in + r * PC_POSE_WIDTH, n2 = 0.0f;
        for (c = 0; c < PC_POSE_WIDTH; c++) {
            seed = seed * 1664525u + 1013904223u;
            p[c] = (float)(seed >> 8) / 8388608.0f - 1.0f; /* [-1, 1) */
            if (c >= 3)
                n2 += p[c] * p[c];
        }
        for (c = 3; c < PC_POSE_WIDTH; c++)
            p[c] /= sqrtf(n2);
    }
    for (r = 0; r < batch->batch; r++) { /* times: [0, 2 h) s */
        seed = seed * 1664525u + 1013904223u;
        t[r] = (float)(seed >> 8) / 8388608.0f * 3600.0f;
    }
    /* A probe the model cannot run says nothing about rows: pc_run will report it. */
    memcpy(batch->in, in, batch->batch * PC_POSE_WIDTH * sizeof(float));
    if (batch->t)
        memcpy(batch->t, t, batch->batch * sizeof(float));
    if (pc_run_steps(m, batch) != PC_OK)
        return pc_forget_probe(m);
    memcpy(out, batch->out, batch->batch * PC_POSE_WIDTH * sizeof(float));
    for (r = 0; r < batch->batch; r++) {
        memcpy(one->in, in + r * PC_POSE_WIDTH, sizeof(float) * PC_POSE_WIDTH);
        if (one->t)
            one->t[0] = t[r];
        if (pc_run_steps(m, one) != PC_OK)
            return pc_forget_probe(m);
        for (i = 0; i < PC_POSE_WIDTH; i++)
            if (!pc_same_result(one->out[i], out[r * PC_POSE_WIDTH + i]))
                return pc_fail(err, PC_ERR_GRAPH,
                               "graph mixes rows: pose %zu of a %zu-pose batch gives another "
                               "result than alone (column %zu); pc_run needs rows that are "
                               "independent (no reduction, reshape or gather across the batch "
                               "axis)", r, batch->batch, i);
    }
    return PC_OK;
}

/* Numbers of a JSON array such as [[-1, -0.5, 0], [1, 0.5, 1.2]] in the bytes [s, end),
 * read where they lie (a value of any length; a NUL byte is no part of a number), without
 * strtod (which may allocate on small C libraries). Returns the count, or -1 on anything
 * else. */
#define PC_AT (s < end ? *s : '\0')
static int pc_parse_numbers(const char *s, const char *end, double *v, int cap)
{
    int n = 0;
    while (s < end) {
        double x = 0.0, scale = 1.0;
        int sign = 1, e = 0, esign = 1, digits = 0;
        if (PC_AT == '[' || PC_AT == ']' || PC_AT == ',' || PC_AT == ' ') {
            s++;
            continue;
        }
        if (PC_AT == '-' || PC_AT == '+')
            sign = *s++ == '-' ? -1 : 1;
        for (; PC_AT >= '0' && PC_AT <= '9'; s++, digits++)
            x = 10.0 * x + (PC_AT - '0');
        if (PC_AT == '.')
            for (s++; PC_AT >= '0' && PC_AT <= '9'; s++, digits++)
                x += (PC_AT - '0') * (scale *= 0.1);
        if (!digits || n == cap)
            return -1;
        if (PC_AT == 'e' || PC_AT == 'E') {
            s++;
            if (PC_AT == '-' || PC_AT == '+')
                esign = *s++ == '-' ? -1 : 1;
            if (PC_AT < '0' || PC_AT > '9')
                return -1;
            for (; PC_AT >= '0' && PC_AT <= '9' && e < 400; s++)
                e = 10 * e + (PC_AT - '0');
        }
        for (; e > 0; e--)
            x = esign > 0 ? x * 10.0 : x / 10.0;
        v[n++] = sign * x;
    }
    return n;
}
#undef PC_AT

/* A metadata value of bounds: `count` lower then `count` upper numbers, each a finite
 * float32, none above its upper partner. A file whose bounds were edited into NaN,
 * infinity or an inverted box is refused here: pc_run would otherwise let every pose
 * through (or none). */
static pc_status pc_read_bounds(const pc_builder *b, const char *key, pb_slice value, int count,
                                const char *expected, float *lo, float *hi)
{
    const char *text = (const char *)value.data;
    double v[6];
    int k;
    if (pc_parse_numbers(text, text + value.size, v, 2 * count) != 2 * count)
        return pc_fail(b->err, PC_ERR_MALFORMED, "metadata %s is '%.*s', expected %s", key,
                       value.size < 60 ? (int)value.size : 60, text, expected);
    for (k = 0; k < count; k++) {
        /* beyond FLT_MAX the conversion to float would be undefined */
        if (!(fabs(v[k]) <= FLT_MAX && fabs(v[k + count]) <= FLT_MAX))
            return pc_fail(b->err, PC_ERR_MALFORMED, "metadata %s: a bound is not a finite "
                           "float32 in column %d (expected %s)", key, k, expected);
        lo[k] = (float)v[k];
        hi[k] = (float)v[k + count];
        if (!(lo[k] <= hi[k]))
            return pc_fail(b->err, PC_ERR_MALFORMED, "metadata %s: lower bound above upper "
                           "bound in column %d", key, k);
    }
    return PC_OK;
}

/* Metadata read at load: posecorr's exporter marks its models (posecorr_version), whose
 * quaternions in and out must be unit, and records the position box of the training data
 * (input_bounds) and, for a model that takes time, the span of the training times
 * (time_bounds); see posecorr.h. */
static pc_status pc_read_checks(const pc_builder *b, pc_model *m)
{
    pb_reader r;
    pb_slice whole, key, value, box = {NULL, 0}, span = {NULL, 0};
    int more, has_box = 0, has_span = 0;
    pc_status st;
    whole.data = b->file;
    whole.size = b->file_size;
    pb_init(&r, b->file, whole);
    while ((more = onnx_next_meta(b, &r, &key, &value)) == PB_FIELD) {
        if (pb_slice_eq(key, "posecorr_version"))
            m->check_quaternion = 1;
        if (pb_slice_eq(key, "input_bounds")) {
            box = value;
            has_box = 1;
        }
        if (pb_slice_eq(key, "time_bounds")) {
            span = value;
            has_span = 1;
        }
    }
    if (more == PB_ERROR)
        return r.status;
    if (has_box) {
        if ((st = pc_read_bounds(b, "input_bounds", box, 3, "[[x_lo, y_lo, z_lo], [x_hi, y_hi, "
                                 "z_hi]] in metres", m->lo, m->hi)) != PC_OK)
            return st;
        m->has_bounds = 1;
    }
    if (has_span) {
        if ((st = pc_read_bounds(b, "time_bounds", span, 1, "[t_lo, t_hi] in seconds",
                                 &m->t_lo, &m->t_hi)) != PC_OK)
            return st;
        m->has_span = m->takes_time; /* a model without the input t ignores time */
    }
    return PC_OK;
}

/* ---- loading ---------------------------------------------------------------------- */

pc_status pc_load_impl(const void *data, size_t size, const pc_options *opts, int any_io,
                       void *buf, size_t buf_size, pc_model **model, size_t *scratch_used,
                       pc_error *err)
{
    pc_builder b;
    pc_error local;
    pc_status st;
    if (!err)
        err = &local;
    err->status = PC_OK;
    err->message[0] = '\0';
    if (!model)
        return pc_fail(err, PC_ERR_ARGUMENT, "model pointer is NULL");
    *model = NULL;
    if (!data && size)
        return pc_fail(err, PC_ERR_ARGUMENT, "data is NULL");
    if (size == 0)
        return pc_fail(err, PC_ERR_TRUNCATED, "truncated file at byte 0 (empty)");
    memset(&b, 0, sizeof b);
    b.err = err;
    b.file = (const uint8_t *)data;
    b.file_size = size;
    b.any_io = any_io;
    b.cpu_avx2 = -1;
    b.in_place = opts && (opts->flags & PC_LOAD_IN_PLACE);
    if (buf)
        pc_scratch_use_buffer(&b.scratch, buf, buf_size);
    st = pc_scan_graph(&b);
    if (st == PC_OK)
        st = pc_plan_build(&b, opts, buf, buf_size, model);
    if (st == PC_OK && !any_io && (st = pc_read_checks(&b, *model)) != PC_OK) {
        pc_free(*model);
        *model = NULL;
    }
    if (st == PC_ERR_MEMORY && buf && err->status == PC_ERR_MEMORY)
        pc_fail(err, st, "the %zu-byte buffer is too small for this model (pc_required_bytes)",
                buf_size);
    /* Scratch alone before the arena is placed, scratch beside the arena after. */
    if (scratch_used && st == PC_OK)
        *scratch_used = b.peak_unplaced > b.scratch.peak + (*model)->arena_bytes
                            ? b.peak_unplaced - (*model)->arena_bytes
                            : b.scratch.peak;
    pc_scratch_release(&b.scratch);
    if (st == PC_OK && !any_io && (st = pc_check_rows(*model, err)) != PC_OK) {
        pc_free(*model);
        *model = NULL;
    }
    if (st != PC_OK && err->status == PC_OK)
        pc_fail(err, st, "%s", pc_status_name(st));
    return st;
}

pc_status pc_load_memory(const void *data, size_t size, const pc_options *opts,
                         pc_model **model, pc_error *err)
{
    return pc_load_impl(data, size, opts, 0, NULL, 0, model, NULL, err);
}

pc_status pc_required_bytes(const void *data, size_t size, const pc_options *opts,
                            size_t *bytes, pc_error *err)
{
    pc_model *m;
    size_t scratch;
    pc_status st;
    if (!bytes)
        return pc_fail(err, PC_ERR_ARGUMENT, "bytes pointer is NULL");
    *bytes = 0;
    st = pc_load_impl(data, size, opts, 0, NULL, 0, &m, &scratch, err);
    if (st != PC_OK)
        return st;
    /* Scratch from the aligned start, the arena aligned down at the end. */
    *bytes = PC_ALIGN + scratch + m->arena_bytes + PC_ALIGN;
    pc_free(m);
    return PC_OK;
}

pc_status pc_load_into(const void *data, size_t size, const pc_options *opts, void *buffer,
                       size_t buffer_size, pc_model **model, pc_error *err)
{
    if (!buffer) {
        if (model)
            *model = NULL;
        return pc_fail(err, PC_ERR_ARGUMENT, "buffer is NULL");
    }
    return pc_load_impl(data, size, opts, 0, buffer, buffer_size, model, NULL, err);
}

pc_status pc_load_file(const char *path, const pc_options *opts, pc_model **model,
                       pc_error *err)
{
    FILE *fp;
    long len;
    uint8_t *buf;
    pc_status st;
    pc_error local;
    if (!err)
        err = &local;
    if (model)
        *model = NULL;
    if (!path || !model)
        return pc_fail(err, PC_ERR_ARGUMENT, "path or model pointer is NULL");
    fp = fopen(path, "rb");
    if (!fp)
        return pc_fail(err, PC_ERR_IO, "cannot open '%s'", path);
    if (fseek(fp, 0, SEEK_END) != 0 || (len = ftell(fp)) < 0 || fseek(fp, 0, SEEK_SET) != 0) {
        fclose(fp);
        return pc_fail(err, PC_ERR_IO, "cannot determine the size of '%s'", path);
    }
    /* A folder opens and seeks on some C libraries, its size reading as LONG_MAX: one byte
     * read first makes it "cannot read", not "out of memory". */
    if ((getc(fp) == EOF && ferror(fp)) || fseek(fp, 0, SEEK_SET) != 0) {
        fclose(fp);
        return pc_fail(err, PC_ERR_IO, "cannot read '%s': not a regular file (a folder?)", path);
    }
    buf = (uint8_t *)malloc(len > 0 ? (size_t)len : 1);
    if (!buf) {
        fclose(fp);
        return pc_fail(err, PC_ERR_MEMORY, "out of memory reading '%s'", path);
    }
    if (len > 0 && fread(buf, 1, (size_t)len, fp) != (size_t)len) {
        fclose(fp);
        free(buf);
        return pc_fail(err, PC_ERR_IO, "cannot read '%s'", path);
    }
    fclose(fp);
    st = pc_load_memory(buf, (size_t)len, opts, model, err);
    free(buf);
    return st;
}

void pc_free(pc_model *model)
{
    if (model && model->owns_arena)
        free(model);
}

/* ---- accessors -------------------------------------------------------------------- */

int pc_version(void)
{
    return PC_VERSION_NUMBER;
}

size_t pc_metadata_count(const pc_model *model)
{
    return model ? model->n_meta : 0;
}

const char *pc_metadata_key(const pc_model *model, size_t index)
{
    return model && index < model->n_meta ? model->meta_key[index] : NULL;
}

const char *pc_metadata_value(const pc_model *model, size_t index)
{
    return model && index < model->n_meta ? model->meta_value[index] : NULL;
}

const char *pc_metadata_lookup(const pc_model *model, const char *key)
{
    size_t i;
    if (!model || !key)
        return NULL;
    for (i = 0; i < model->n_meta; i++)
        if (strcmp(model->meta_key[i], key) == 0)
            return model->meta_value[i];
    return NULL;
}

size_t pc_max_batch(const pc_model *model) { return model ? model->max_batch : 0; }
size_t pc_arena_bytes(const pc_model *model) { return model ? model->arena_bytes : 0; }
size_t pc_step_count(const pc_model *model)
{
    return model && model->n_plans ? model->plans[0].n_steps : 0;
}
size_t pc_node_count(const pc_model *model) { return model ? model->n_nodes : 0; }
const char *pc_model_message(const pc_model *model) { return model ? model->message : ""; }

int pc_model_takes_time(const pc_model *model) { return model ? model->takes_time : 0; }
