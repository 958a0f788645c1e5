/* posecorr-run MODEL.onnx [--binary [--timed]] [--strict] [--allow-unbounded] [--allow-unsigned]
 *
 * Streams poses through a corrector: one CSV line "x,y,z,qw,qx,qy,qz" in, one line out,
 * flushed per pose so it can sit in a pipe next to a tracker. An optional 8th value
 * "x,y,z,qw,qx,qy,qz,t" is the pose's time t (s since the session's start), passed to
 * models that take time (pc_model_takes_time; others ignore it); without it such a model
 * corrects the pose as at t = 0. --binary reads and writes raw little-endian float32
 * records of 7 values instead; with --timed each record read holds 8, t the 8th (a record
 * has no room for an optional value, so the width is said once; a model that takes time
 * read without it is named on stderr at the start). A first line of 7 (or 8) names is a
 * header, passed through.
 * Numbers are read as the table reader reads them: plain decimal notation (nan and inf read,
 * then refused as non-finite; a hexadecimal float such as 0x1p-5 is a bad line), on lines of
 * any length. The model must be a regular file: a FIFO, a device or a folder is refused.
 *
 * A bad line (or a record the model refuses) is answered on stderr with its line (record)
 * number and the reason, and on stdout with a line (record) of seven NaN, so that output
 * line k still belongs to input line k; the stream goes on, because one glitch on a
 * controller's pipe must not end it. The exit status is then 1 at the end of input.
 * --strict stops at the first bad line instead (exit 1). A trailing partial binary record
 * is reported (exit 1), never dropped in silence. --allow-unbounded and --allow-unsigned
 * load a model without input_bounds/correction_reach or without model_digest
 * (PC_LOAD_ALLOW_UNBOUNDED, PC_LOAD_ALLOW_UNSIGNED: models of other producers). */
#include "posecorr.h"

#include <float.h>
#include <math.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#if defined(__unix__) || defined(__APPLE__)
#include <sys/stat.h>
#endif

#define USAGE "usage: %s MODEL.onnx [--binary [--timed]] [--strict] [--allow-unbounded] " \
              "[--allow-unsigned] < poses > corrected\n"

/* A line of any length reads: runs of blanks are kept as one (they only separate
 * numbers), the buffer grows for the other bytes, and a line already bad (a NUL byte,
 * what /dev/zero on stdin gives) is read to its end without keeping more, so an endless
 * one costs no memory. */
typedef struct {
    char *data;
    size_t cap;
    int too_long; /* the line outgrew the memory that could be allocated */
    int has_nul;  /* the line held a NUL byte: C strings would end there */
} line_buffer;

/* Room for one more byte and the terminating NUL; 0 when memory runs out. */
static int line_reserve(line_buffer *buf, size_t len)
{
    char *grown;
    size_t cap;
    if (len + 2 <= buf->cap)
        return 1;
    cap = buf->cap ? 2 * buf->cap : 256;
    if (cap < buf->cap || !(grown = (char *)realloc(buf->data, cap)))
        return 0;
    buf->data = grown;
    buf->cap = cap;
    return 1;
}

/* Reads one line (without its newline) into buf; returns 0 at end of input, 1 otherwise. */
static int read_line(FILE *in, line_buffer *buf)
{
    size_t len = 0;
    int c;
    buf->too_long = buf->has_nul = 0;
    if (!line_reserve(buf, 0))
        buf->too_long = 1;
    while ((c = getc(in)) != EOF && c != '\n') {
        if (c == '\0')
            buf->has_nul = 1;
        if ((c == ' ' || c == '\t') && len > 0 && (buf->data[len - 1] == ' ' || buf->data[len - 1] == '\t'))
            continue;
        if (buf->has_nul || buf->too_long)
            continue;
        if (line_reserve(buf, len))
            buf->data[len++] = (char)c;
        else
            buf->too_long = 1;
    }
    if (buf->data)
        buf->data[len] = '\0';
    return (c == EOF && len == 0 && !buf->too_long && !buf->has_nul) ? 0 : 1;
}

/* What a line's numbers hold that no pose may: hexadecimal notation, or a finite value
 * beyond float32's range (strtof would make it infinite, and pc_run would call it "not
 * finite"); column is the first such value's (PC_POSE_WIDTH: the time t), -1 if none. */
typedef struct line_faults {
    int hex, column;
    double value;
} line_faults;

/* strtod, restricted to what the table reader takes: plain decimal notation, and nan or
 * inf (which pc_run then refuses as non-finite, naming the column). A hexadecimal float
 * such as 0x1p-5 is no tracker's output: faults->hex is set and nothing is read. A finite
 * value beyond float32 (its float would be inf) is noted in faults; 0 stands for it. */
static float read_number(const char *p, char **end, int column, line_faults *faults)
{
    const char *q = p;
    const double v = strtod(p, end);
    if (*end == p)
        return 0.0f;
    while (*q == ' ' || *q == '\t')
        q++;
    if (*q == '+' || *q == '-')
        q++;
    if (q[0] == '0' && (q[1] == 'x' || q[1] == 'X')) {
        faults->hex = 1;
        *end = (char *)p;
        return 0.0f;
    }
    if (fabs(v) > FLT_MAX && fabs(v) <= DBL_MAX) {
        if (faults->column < 0) {
            faults->column = column;
            faults->value = v;
        }
        return 0.0f;
    }
    return (float)v;
}

static int parse_line(const char *line, float *v, line_faults *faults)
{
    const char *p = line;
    int k;
    for (k = 0; k < PC_POSE_WIDTH; k++) {
        char *end;
        while (*p == ' ' || *p == '\t')
            p++;
        v[k] = read_number(p, &end, k, faults);
        if (end == p)
            return 0;
        p = end;
        while (*p == ' ' || *p == '\t')
            p++;
        if (k < PC_POSE_WIDTH - 1) {
            if (*p != ',')
                return 0;
            p++;
        }
    }
    while (*p == ' ' || *p == '\t' || *p == '\r')
        p++;
    return *p == '\0';
}

/* Splits an optional 8th value (the time t) off a text line: returns 1 and cuts the line
 * before it when there is one, 0 (line untouched) otherwise. */
static int split_time(char *line, float *t, line_faults *faults)
{
    char *p = line, *end;
    int commas = 0;
    while (*p && !(*p == ',' && ++commas == PC_POSE_WIDTH))
        p++;
    if (!*p)
        return 0;
    *t = read_number(p + 1, &end, PC_POSE_WIDTH, faults);
    if (end == p + 1)
        return 0;
    while (*end == ' ' || *end == '\t' || *end == '\r' || *end == '\n')
        end++;
    if (*end)
        return 0;
    *p = '\0';
    return 1;
}

/* A header names the 7 (or 8, with t) columns: that many fields, none a number. Any other
 * line that is not a pose is a bad line, answered with NaN like the rest. */
static int is_header(const char *line)
{
    int fields = 0;
    const char *p = line;
    for (;;) {
        const char *start = p;
        char *end;
        while (*p && *p != ',')
            p++;
        while (start < p && (*start == ' ' || *start == '\t'))
            start++;
        if (start == p)
            return 0; /* an empty field */
        strtof(start, &end);
        if (end != start)
            return 0; /* a field that reads as a number */
        fields++;
        if (!*p)
            break;
        p++;
    }
    return fields == PC_POSE_WIDTH || fields == PC_POSE_WIDTH + 1;
}

static int is_blank(const char *s)
{
    for (; *s; s++)
        if (*s != ' ' && *s != '\t' && *s != '\r')
            return 0;
    return 1;
}

static void fill_nan(float *out)
{
    int k;
    for (k = 0; k < PC_POSE_WIDTH; k++)
        out[k] = (float)NAN;
}

static int write_text_pose(const float *out)
{
    int n = printf("%.9g,%.9g,%.9g,%.9g,%.9g,%.9g,%.9g\n", out[0], out[1], out[2], out[3],
                   out[4], out[5], out[6]);
    return n > 0 && fflush(stdout) == 0;
}

/* A record's floats between the stream's little-endian bytes and the host's order. */
static void float_from_le(const unsigned char *b, float *x)
{
    const uint32_t u = (uint32_t)b[0] | (uint32_t)b[1] << 8 | (uint32_t)b[2] << 16 |
                       (uint32_t)b[3] << 24;
    memcpy(x, &u, sizeof *x);
}

static void float_to_le(float x, unsigned char *b)
{
    uint32_t u;
    int i;
    memcpy(&u, &x, sizeof u);
    for (i = 0; i < 4; i++)
        b[i] = (unsigned char)(u >> (8 * i));
}

static int write_binary_pose(const float *out)
{
    unsigned char record[4 * PC_POSE_WIDTH];
    int i;
    for (i = 0; i < PC_POSE_WIDTH; i++)
        float_to_le(out[i], record + 4 * i);
    return fwrite(record, 1, sizeof record, stdout) == sizeof record && fflush(stdout) == 0;
}

/* pc_run's message for a line (record) that names the pose already: a refusal reads
 * "pose I: CLAUSE" (posecorr.h), I the pose's index in the call, 0 here where every call is
 * one pose; "line 2: pose 0: ..." would name one pose twice, the second time wrongly. */
static const char *refusal(const pc_model *model)
{
    static const char one_pose[] = "pose 0: ";
    const char *message = pc_model_message(model);
    return strncmp(message, one_pose, sizeof one_pose - 1) == 0 ? message + sizeof one_pose - 1
                                                                 : message;
}

/* Records of 7 float32, or 8 with the pose's time last (timed). */
static int run_binary(pc_model *model, int strict, int timed)
{
    const int values = PC_POSE_WIDTH + (timed ? 1 : 0);
    const size_t width = 4 * (size_t)values;
    unsigned char bytes[4 * (PC_POSE_WIDTH + 1)];
    float in[PC_POSE_WIDTH + 1], out[PC_POSE_WIDTH];
    unsigned long record = 0;
    int failed = 0, i;
    size_t got;
    while ((got = fread(bytes, 1, width, stdin)) == width) {
        pc_status st;
        record++;
        for (i = 0; i < values; i++)
            float_from_le(bytes + 4 * i, in + i);
        if ((st = pc_run_timed(model, in, timed ? in + PC_POSE_WIDTH : NULL, 1, out)) != PC_OK) {
            fprintf(stderr, "posecorr-run: record %lu: %s: %s\n", record, pc_status_name(st),
                    refusal(model));
            if (strict)
                return 1;
            failed = 1;
            fill_nan(out);
        }
        if (!write_binary_pose(out))
            return 1;
    }
    if (got != 0) {
        fprintf(stderr, "posecorr-run: record %lu: partial record of %lu bytes at the end of "
                        "input (a record is %lu bytes: %d float32)\n",
                record + 1, (unsigned long)got, (unsigned long)width, values);
        return 1;
    }
    if (ferror(stdin)) {
        fprintf(stderr, "posecorr-run: read error on standard input\n");
        return 1;
    }
    return failed;
}

static int run_text(pc_model *model, int strict)
{
    float in[PC_POSE_WIDTH], out[PC_POSE_WIDTH];
    line_buffer buf = {NULL, 0, 0, 0};
    unsigned long line_no = 0;
    int failed = 0, status = 0;
    while (read_line(stdin, &buf) == 1) {
        char *line = buf.data;
        pc_status st;
        float t = 0.0f;
        int has_t = 0, refused = 0;
        line_faults faults = {0, -1, 0.0};
        line_no++;
        if (!buf.has_nul && !buf.too_long && (line[0] == '#' || is_blank(line)))
            continue;
        if (!buf.has_nul && !buf.too_long && line_no == 1 && is_header(line)) {
            /* a CSV header: pass it through */
            if (printf("%s\n", line) < 0 || fflush(stdout) != 0) {
                status = 1;
                break;
            }
            continue;
        }
        if (!buf.has_nul && !buf.too_long)
            has_t = split_time(line, &t, &faults);
        if (buf.has_nul || buf.too_long || !parse_line(line, in, &faults) || faults.hex) {
            fprintf(stderr, "posecorr-run: line %lu: expected 7 comma-separated numbers "
                            "x,y,z,qw,qx,qy,qz and an optional 8th, t%s\n", line_no,
                    buf.has_nul ? " (the line holds a NUL byte)"
                    : buf.too_long ? " (out of memory reading the line)"
                    : faults.hex ? " in plain decimal notation (like -0.125 or 1.5e-3), not hexadecimal" : "");
            refused = 1;
        } else if (faults.column >= 0 && (faults.column < PC_POSE_WIDTH || pc_model_takes_time(model))) {
            static const char *const names[PC_POSE_WIDTH + 1] = {"x", "y", "z", "qw", "qx", "qy",
                                                                "qz", "t"};
            static const char *const units[PC_POSE_WIDTH + 1] = {" m", " m", " m", "", "", "", "",
                                                                " s"};
            fprintf(stderr, "posecorr-run: line %lu: %s = %.7g%s does not fit in float32, the "
                            "numbers the model computes in (their largest is %.7g)\n", line_no,
                    names[faults.column], faults.value, units[faults.column], (double)FLT_MAX);
            refused = 1;
        } else if ((st = pc_run_timed(model, in, has_t ? &t : NULL, 1, out)) != PC_OK) {
            fprintf(stderr, "posecorr-run: line %lu: %s: %s\n", line_no, pc_status_name(st),
                    refusal(model));
            refused = 1;
        }
        if (refused) { /* answered with NaN, or with --strict the end */
            if (strict) {
                status = 1;
                break;
            }
            failed = 1;
            fill_nan(out);
        }
        if (!write_text_pose(out)) {
            status = 1;
            break;
        }
    }
    free(buf.data);
    return status ? status : failed;
}

/* What a model path is when it is not a regular file, or NULL: refused in the words of
 * `posecorr info` and the shim (pc_load_file refuses it too, in the library's words). */
static const char *not_a_file(const char *path)
{
#if defined(__unix__) || defined(__APPLE__)
    struct stat st;
    if (stat(path, &st) != 0 || S_ISREG(st.st_mode))
        return NULL; /* a missing file: pc_load_file says it cannot open it */
    return S_ISDIR(st.st_mode) ? "a folder" : S_ISFIFO(st.st_mode) ? "a FIFO"
         : S_ISCHR(st.st_mode) ? "a character device" : S_ISBLK(st.st_mode) ? "a block device"
         : "not a regular file";
#else
    (void)path;
    return NULL;
#endif
}

int main(int argc, char **argv)
{
    const char *path = NULL;
    int binary = 0, timed = 0, strict = 0, i, status;
    pc_model *model;
    pc_options opts = {0, 0, 0};
    pc_error err;
    pc_status st;

    for (i = 1; i < argc; i++) {
        if (strcmp(argv[i], "--binary") == 0)
            binary = 1;
        else if (strcmp(argv[i], "--timed") == 0)
            timed = 1;
        else if (strcmp(argv[i], "--allow-unbounded") == 0)
            opts.flags |= PC_LOAD_ALLOW_UNBOUNDED;
        else if (strcmp(argv[i], "--allow-unsigned") == 0)
            opts.flags |= PC_LOAD_ALLOW_UNSIGNED;
        else if (strcmp(argv[i], "--strict") == 0)
            strict = 1;
        else if (strcmp(argv[i], "-h") == 0 || strcmp(argv[i], "--help") == 0) {
            printf(USAGE, argv[0]);
            return 0;
        } else if (!path)
            path = argv[i];
        else {
            fprintf(stderr, "posecorr-run: unexpected argument '%s'\n", argv[i]);
            return 2;
        }
    }
    if (!path) {
        fprintf(stderr, USAGE, argv[0]);
        return 2;
    }
    if (timed && !binary) {
        fprintf(stderr, "posecorr-run: --timed is for --binary records (a text line takes its "
                        "time as an optional 8th value)\n");
        return 2;
    }
    if (not_a_file(path)) {
        fprintf(stderr, "posecorr-run: %s: is %s, expected a file\n", path, not_a_file(path));
        return 1;
    }
    st = pc_load_file(path, &opts, &model, &err);
    if (st != PC_OK) {
        fprintf(stderr, "posecorr-run: %s: %s\n", path, err.message);
        return 1;
    }
    if (binary && !timed && pc_model_takes_time(model))
        fprintf(stderr, "posecorr-run: %s: the model takes time t; records of 7 float32 are "
                        "corrected as at t = 0 (--timed reads records of 8, t last)\n", path);
    status = binary ? run_binary(model, strict, timed) : run_text(model, strict);
    pc_free(model);
    return status;
}
