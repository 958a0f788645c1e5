/* hot_swap MODEL.onnx < poses > corrected
 *
 * The pattern for replacing a corrector while a controller runs, without ROS and without
 * a restart (posecorr.h, "Threads"): the control loop owns the model it runs; a loader
 * thread watches the model file, loads a new version beside the old one, checks it, and
 * hands it over through one atomic pointer. The loop takes it between two poses, so every
 * output comes from exactly one model and no pose waits for a load. The old model goes back
 * to the loader thread, which frees it: the loop never calls malloc or free.
 *
 * Input: one pose per line, "x,y,z,qw,qx,qy,qz". Output: "generation,x,y,z,qw,qx,qy,qz"
 * per pose (generation 1 is the model at start; a refused pose gives NaN values). On
 * stderr: "loaded generation G (pose P)" when the loop takes a new model, and "refused
 * FILE: reason" when a new file fails to load or to pass the check (the running model
 * keeps serving). A file is (re)read when its size, modification time or inode changes,
 * and only once it has stayed the same for two polls: a writer that replaces the file
 * atomically (posecorr's exporter does) is never read half-written, and a corrupt file is
 * refused by the loader anyway.
 *
 * Build: cc -std=c11 -pthread hot_swap.c -lposecorr (C11 for <stdatomic.h>). */
#define _POSIX_C_SOURCE 200809L
#include <posecorr.h>

#include <math.h>
#include <pthread.h>
#include <stdatomic.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>
#include <time.h>

#define POLL_MS 10

typedef struct shared {
    const char *path;
    struct stat start; /* the file as it was before the first load */
    int have_start;
    _Atomic(pc_model *) incoming; /* loader -> loop: a checked model, or NULL */
    _Atomic(pc_model *) retired;  /* loop -> loader: the model it stopped using */
    atomic_int stop;
} shared;

/* The centre of the model's training box (metadata input_bounds), unturned: a pose it
 * must take. The origin for a model without the box. */
static void probe_pose(const pc_model *m, float pose[7])
{
    const char *box = pc_metadata_lookup(m, "input_bounds");
    float lo[3], hi[3];
    int k;
    memset(pose, 0, 7 * sizeof *pose);
    pose[3] = 1.0f;
    if (box && sscanf(box, " [ [ %f , %f , %f ] , [ %f , %f , %f ] ]", &lo[0], &lo[1], &lo[2],
                      &hi[0], &hi[1], &hi[2]) == 6)
        for (k = 0; k < 3; k++)
            pose[k] = 0.5f * (lo[k] + hi[k]);
}

/* A new model must answer the probe pose like a corrector: a finite pose with a unit
 * quaternion, within the model's correction_reach (pc_run checks all three) — on this
 * thread, before the loop ever sees it. */
static int check_model(pc_model *m, char *why, size_t size)
{
    float probe[7], out[7];
    probe_pose(m, probe);
    if (pc_run(m, probe, 1, out) != PC_OK) {
        snprintf(why, size, "probe pose: %s", pc_model_message(m));
        return 0;
    }
    return 1;
}

static void sleep_ms(long ms)
{
    struct timespec ts;
    ts.tv_sec = ms / 1000;
    ts.tv_nsec = (ms % 1000) * 1000000L;
    nanosleep(&ts, NULL);
}

static int same_file(const struct stat *a, const struct stat *b)
{
    return a->st_size == b->st_size && a->st_ino == b->st_ino &&
           a->st_mtim.tv_sec == b->st_mtim.tv_sec && a->st_mtim.tv_nsec == b->st_mtim.tv_nsec;
}

static void *loader(void *arg)
{
    shared *s = (shared *)arg;
    struct stat seen = s->start, last;
    int have_seen = s->have_start, stable = 0;
    memset(&last, 0, sizeof last);
    while (!atomic_load(&s->stop)) {
        struct stat now;
        pc_model *old = atomic_exchange(&s->retired, NULL);
        if (old)
            pc_free(old);
        sleep_ms(POLL_MS);
        if (stat(s->path, &now) != 0)
            continue;
        if (have_seen && same_file(&now, &seen))
            continue;
        /* changed: wait until it stays the same for two polls */
        if (!same_file(&now, &last)) {
            last = now;
            stable = 0;
            continue;
        }
        if (++stable < 2)
            continue;
        seen = now;
        have_seen = 1;
        {
            pc_model *m = NULL;
            pc_error err;
            char why[PC_MESSAGE_SIZE];
            if (pc_load_file(s->path, NULL, &m, &err) != PC_OK) {
                fprintf(stderr, "refused %s: %s\n", s->path, err.message);
                continue;
            }
            if (!check_model(m, why, sizeof why)) {
                fprintf(stderr, "refused %s: %s\n", s->path, why);
                pc_free(m);
                continue;
            }
            /* a model the loop has not taken yet is replaced by the newer one */
            m = atomic_exchange(&s->incoming, m);
            if (m)
                pc_free(m);
        }
    }
    return NULL;
}

static int parse_pose(const char *line, float *p)
{
    int k = 0;
    char *end;
    const char *at = line;
    for (; k < 7; k++) {
        p[k] = strtof(at, &end);
        if (end == at)
            return 0;
        at = end;
        if (k < 6) {
            if (*at != ',')
                return 0;
            at++;
        }
    }
    return 1;
}

int main(int argc, char **argv)
{
    shared s;
    pthread_t thread;
    pc_model *current = NULL;
    pc_error err;
    char line[512];
    unsigned long pose = 0;
    int generation = 1;
    if (argc != 2) {
        fprintf(stderr, "usage: %s MODEL.onnx < poses > corrected\n", argv[0]);
        return 2;
    }
    /* Seen before the load, not by the loader when it starts: on a busy machine the thread
     * may first run after a replacement, take the new file for the one loaded, and never
     * load it. A replacement between this and the load is loaded once more, harmlessly. */
    s.have_start = stat(argv[1], &s.start) == 0;
    if (pc_load_file(argv[1], NULL, &current, &err) != PC_OK) {
        fprintf(stderr, "%s: %s\n", argv[1], err.message);
        return 1;
    }
    s.path = argv[1];
    atomic_init(&s.incoming, NULL);
    atomic_init(&s.retired, NULL);
    atomic_init(&s.stop, 0);
    if (pthread_create(&thread, NULL, loader, &s) != 0) {
        fprintf(stderr, "cannot start the loader thread\n");
        return 1;
    }
    while (fgets(line, sizeof line, stdin)) {
        float in[7], out[7];
        /* between two poses: take a new model if one is ready */
        pc_model *next = atomic_exchange(&s.incoming, NULL);
        if (next) {
            pc_model *old = current;
            current = next;
            generation++;
            fprintf(stderr, "loaded generation %d (pose %lu)\n", generation, pose);
            /* the loader frees it; one still waiting there is freed here first */
            old = atomic_exchange(&s.retired, old);
            if (old)
                pc_free(old);
        }
        if (!parse_pose(line, in) || pc_run(current, in, 1, out) != PC_OK) {
            int k;
            for (k = 0; k < 7; k++)
                out[k] = NAN;
        }
        printf("%d,%.9g,%.9g,%.9g,%.9g,%.9g,%.9g,%.9g\n", generation, out[0], out[1], out[2],
               out[3], out[4], out[5], out[6]);
        fflush(stdout);
        pose++;
    }
    atomic_store(&s.stop, 1);
    pthread_join(thread, NULL);
    {
        pc_model *m = atomic_exchange(&s.incoming, NULL);
        pc_free(m);
        pc_free(atomic_exchange(&s.retired, NULL));
    }
    pc_free(current);
    return 0;
}
