/* posecorr-run MODEL.onnx [--binary]
 *
 * Streams poses through a corrector: one CSV line "x,y,z,qw,qx,qy,qz" in, one line out,
 * flushed per pose so it can sit in a pipe next to a tracker. An optional 8th value
 * "x,y,z,qw,qx,qy,qz,t" is the pose's time t (s since the session's start), passed to
 * models that take time (pc_model_takes_time; others ignore it); without it such a
 * model corrects the pose as at t = 0. --binary reads and writes
 * raw little-endian float32 records of 7 values instead. Errors go to stderr with the
 * line (or record) number and end the stream with exit status 1: a controller must not
 * silently lose the pairing between input and output lines. */
#include "posecorr.h"

#include <ctype.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

static int parse_line(const char *line, float *v)
{
    const char *p = line;
    int k;
    for (k = 0; k < PC_POSE_WIDTH; k++) {
        char *end;
        while (*p == ' ' || *p == '\t')
            p++;
        v[k] = strtof(p, &end);
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
    while (*p == ' ' || *p == '\t' || *p == '\r' || *p == '\n')
        p++;
    return *p == '\0';
}

/* When the line has an 8th comma-separated value that is a number, stores it in *t, cuts
 * the line before it (leaving the 7 pose values) and returns 1; otherwise leaves the line
 * as it is and returns 0. */
static int split_time(char *line, float *t)
{
    char *p = line, *end;
    int commas = 0;
    while (*p && !(*p == ',' && ++commas == PC_POSE_WIDTH))
        p++;
    if (!*p)
        return 0;
    *t = strtof(p + 1, &end);
    if (end == p + 1)
        return 0;
    while (*end == ' ' || *end == '\t' || *end == '\r' || *end == '\n')
        end++;
    if (*end)
        return 0;
    *p = '\0';
    return 1;
}

static int has_letter(const char *s)
{
    for (; *s; s++)
        if (isalpha((unsigned char)*s) && *s != 'e' && *s != 'E')
            return 1;
    return 0;
}

int main(int argc, char **argv)
{
    const char *path = NULL;
    int binary = 0, i;
    pc_model *model;
    pc_error err;
    pc_status st;
    unsigned long line_no = 0;
    char line[4096];
    float in[PC_POSE_WIDTH], out[PC_POSE_WIDTH], t = 0.0f;
    int has_t;

    for (i = 1; i < argc; i++) {
        if (strcmp(argv[i], "--binary") == 0)
            binary = 1;
        else if (strcmp(argv[i], "-h") == 0 || strcmp(argv[i], "--help") == 0) {
            printf("usage: %s MODEL.onnx [--binary] < poses > corrected\n", argv[0]);
            return 0;
        } else if (!path)
            path = argv[i];
        else {
            fprintf(stderr, "posecorr-run: unexpected argument '%s'\n", argv[i]);
            return 2;
        }
    }
    if (!path) {
        fprintf(stderr, "usage: %s MODEL.onnx [--binary] < poses > corrected\n", argv[0]);
        return 2;
    }
    st = pc_load_file(path, NULL, &model, &err);
    if (st != PC_OK) {
        fprintf(stderr, "posecorr-run: %s: %s\n", path, err.message);
        return 1;
    }
    if (binary) {
        while (fread(in, sizeof in, 1, stdin) == 1) {
            line_no++;
            st = pc_run(model, in, 1, out);
            if (st != PC_OK) {
                fprintf(stderr, "posecorr-run: record %lu: %s: %s\n", line_no,
                        pc_status_name(st), pc_model_message(model));
                pc_free(model);
                return 1;
            }
            if (fwrite(out, sizeof out, 1, stdout) != 1) {
                pc_free(model);
                return 1;
            }
            fflush(stdout);
        }
        pc_free(model);
        return 0;
    }
    while (fgets(line, sizeof line, stdin)) {
        line_no++;
        if (line[0] == '\n' || line[0] == '\r' || line[0] == '#' || line[0] == '\0')
            continue;
        if (!strchr(line, '\n') && !feof(stdin)) {
            fprintf(stderr, "posecorr-run: line %lu: line too long\n", line_no);
            pc_free(model);
            return 1;
        }
        has_t = split_time(line, &t);
        if (!parse_line(line, in)) {
            if (line_no == 1 && has_letter(line)) { /* a CSV header: pass it through */
                fputs(line, stdout);
                fflush(stdout);
                continue;
            }
            fprintf(stderr, "posecorr-run: line %lu: expected 7 comma-separated numbers "
                            "x,y,z,qw,qx,qy,qz\n", line_no);
            pc_free(model);
            return 1;
        }
        st = pc_run_timed(model, in, has_t ? &t : NULL, 1, out);
        if (st != PC_OK) {
            fprintf(stderr, "posecorr-run: line %lu: %s: %s\n", line_no, pc_status_name(st),
                    pc_model_message(model));
            pc_free(model);
            return 1;
        }
        printf("%.9g,%.9g,%.9g,%.9g,%.9g,%.9g,%.9g\n", out[0], out[1], out[2], out[3], out[4],
               out[5], out[6]);
        fflush(stdout);
    }
    pc_free(model);
    return 0;
}
