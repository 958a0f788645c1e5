/*
 * posecorr.h - the one public header of libposecorr.
 *
 * libposecorr loads a posecorr corrector (.onnx, opset PC_OPSET_MIN..PC_OPSET_MAX, the
 * operator subset of export/operators.txt) and applies it to tracker poses:
 *
 *     input  "pose"      float32 [N,7] = x, y, z, qw, qx, qy, qz
 *     input  "t"         float32 [N], optional: seconds since the session's start, only in
 *                        models with a time-dependent effect (drift); see pc_run_timed
 *     output "corrected" float32 [N,7]
 *
 * Everything the model needs at run time lives in one arena allocated by pc_load_*;
 * pc_run never allocates, never blocks and touches no global state.
 *
 * Threads. The library has no global state: pc_load_* and pc_required_bytes may run on any
 * thread at any time, also while other models run. Safe to share: the library, the bytes
 * a model was loaded from, and one model's read-only accessors (metadata, counts, which
 * may run beside each other and beside pc_run). Not safe to share: a pc_model for pc_run.
 * It holds one arena, written by every pc_run (its buffers and its message), so two
 * overlapping pc_run calls on one model corrupt each other's poses: pc_run, pc_run_timed,
 * pc_model_message and pc_free of one model must not overlap. Threads that share a model
 * take a lock around each pc_run and the pc_model_message that follows it (the Python
 * shim's Corrector does); threads that should run in parallel load one model each from
 * the same bytes (with PC_LOAD_IN_PLACE they share the weights, not the arena). To swap a model while a
 * controller runs, load and check the new one on another thread (it is not shared yet),
 * hand it over through one atomic pointer, take it between two poses, and give the old one
 * back to be freed once the controller no longer uses it: runtime_c/examples/hot_swap.c.
 *
 * Every function that can fail returns a pc_status; the human-readable context (which
 * operator, which node, which byte) is in the pc_error filled by the loader or, after
 * pc_run, in pc_model_message().
 */
#ifndef POSECORR_H
#define POSECORR_H

#include <stddef.h>

#ifdef __cplusplus
extern "C" {
#endif

#if defined(PC_BUILDING_LIBRARY) && defined(__GNUC__)
#define PC_API __attribute__((visibility("default")))
#else
#define PC_API
#endif

#define PC_VERSION_MAJOR 0
#define PC_VERSION_MINOR 6
#define PC_VERSION_PATCH 0
/* What pc_version() returns for the library this header belongs to. */
#define PC_VERSION_NUMBER (PC_VERSION_MAJOR * 10000 + PC_VERSION_MINOR * 100 + PC_VERSION_PATCH)

/* Default-domain opsets the loader accepts (export/operators.txt lists the operators).
 * Past 21 the operators of the list only widened their type lists (ONNX's node tests at
 * these opsets pass, tests/test_onnx_node.py checks the signatures). */
#define PC_OPSET_MIN 13
#define PC_OPSET_MAX 28

/* Poses are 7 floats: x, y, z, qw, qx, qy, qz. */
#define PC_POSE_WIDTH 7
/* Default and upper bound of pc_options.max_batch. */
#define PC_DEFAULT_MAX_BATCH 256
#define PC_MAX_MAX_BATCH 4096
/* Upper bound of pc_options.program_ops: a program's constants keep 16-bit offsets. */
#define PC_MAX_PROGRAM_OPS 4064
#define PC_MESSAGE_SIZE 256

typedef enum pc_status {
    PC_OK = 0,
    PC_ERR_ARGUMENT,       /* NULL pointer or out-of-range argument */
    PC_ERR_IO,             /* file cannot be opened or read */
    PC_ERR_MEMORY,         /* allocation failed at load */
    PC_ERR_TRUNCATED,      /* protobuf message ends inside a field */
    PC_ERR_MALFORMED,      /* protobuf is not valid wire format / ONNX structure */
    PC_ERR_UNSUPPORTED,    /* operator, attribute, data type or opset not supported */
    PC_ERR_CONTRACT,       /* not "pose" float32 [N,7] (+ optional "t" float32 [N]) ->
                            * "corrected" float32 [N,7] */
    PC_ERR_GRAPH,          /* dangling input, cycle, duplicate output, ... */
    PC_ERR_SHAPE,          /* shapes or types of a node do not fit together */
    PC_ERR_NONFINITE,      /* NaN or infinity in an input pose or time */
    PC_ERR_RUNTIME,        /* data-dependent failure: an output not finite or not a unit
                            * quaternion, a Gather index out of range, ... */
    PC_ERR_RANGE,          /* input pose (or time) outside the range the model was fitted
                            * on */
    PC_ERR_QUATERNION,     /* input quaternion not unit (a zero one, a norm of 3, ...) */
    PC_ERR_INTEGRITY,      /* the file's bytes do not give its metadata "model_digest"
                            * (changed after export), or it carries none and the caller
                            * did not pass PC_LOAD_ALLOW_UNSIGNED */
    PC_STATUS_COUNT
} pc_status;

/* PC_VERSION_NUMBER of the library actually linked or loaded (e.g. by a ctypes shim). */
PC_API int pc_version(void);

/* Static description of a status code (never NULL). */
PC_API const char *pc_status_name(pc_status status);

typedef struct pc_error {
    pc_status status;
    char message[PC_MESSAGE_SIZE];
} pc_error;

/* pc_options.flags */
enum {
    /* The caller promises that the model file's bytes (the data passed to pc_load_memory,
     * pc_load_into or pc_required_bytes) stay readable and unchanged for as long as the
     * model is used: in flash, a memory-mapped file, a static array. float32 and int64
     * initializers stored as little-endian raw_data at an aligned offset (posecorr's
     * exporter aligns them to 16 bytes) are then read where they lie instead of being
     * copied into the arena; a big-endian host copies them (byte-swapped) all the same. */
    PC_LOAD_IN_PLACE = 1u << 0,
    /* One-pose plans run every node as its own kernel instead of compiling the small
     * elementwise subgraphs into one-pose programs: slower, and for most models a larger
     * arena (every node's output its own buffer; pc_required_bytes says how much). */
    PC_LOAD_NO_PROGRAMS = 1u << 1,
    /* The metadata strings are not kept (pc_metadata_count is 0): a small target saves
     * their bytes. The checks pc_run takes from them (input_bounds, time_bounds,
     * correction_reach) stay. */
    PC_LOAD_NO_METADATA = 1u << 2,
    /* One-pose programs always run in the library's interpreter, even those whose shape
     * the library carries compiled (the exporter's encoders and decoders): the same
     * results, bit for bit, slower. */
    PC_LOAD_INTERPRET = 1u << 3,
    /* Load a model whose metadata lacks "input_bounds" (the positions it was fitted on)
     * or "correction_reach" (how far its corrections go): its poses are then not checked
     * against them. Without this flag such a model is refused (PC_ERR_CONTRACT). For
     * models of other producers; posecorr's exporter writes both. */
    PC_LOAD_ALLOW_UNBOUNDED = 1u << 4,
    /* Load a model without the metadata "model_digest" (a CRC-32C of the file, see
     * docs/design.md, "Integrity"); without this flag it is refused (PC_ERR_INTEGRITY).
     * A digest that is present is always verified. */
    PC_LOAD_ALLOW_UNSIGNED = 1u << 5
};

typedef struct pc_options {
    /* Largest number of poses evaluated at once; rounded down to a power of two.
     * 0 selects PC_DEFAULT_MAX_BATCH. pc_run handles any n by chunking (plans exist
     * for 1, 16, 256, ... poses and max_batch). */
    size_t max_batch;
    /* PC_LOAD_* flags; 0 for the defaults. A bit no flag of this library names (one of a
     * newer header) is refused (PC_ERR_ARGUMENT), not ignored. */
    unsigned flags;
    /* Element operations a one-pose program may hold while it is compiled (each takes
     * 28 bytes of load-time scratch); 0 selects 512, above PC_MAX_PROGRAM_OPS is taken as
     * that. */
    size_t program_ops;
} pc_options;

typedef struct pc_model pc_model;

/* Load from a buffer; the buffer may be freed once the call returns. opts may be NULL;
 * err may be NULL. On failure *model is NULL. Bytes whose top level is no ONNX model (a
 * text file, say) are PC_ERR_MALFORMED "not a valid ONNX model (unsupported wire type 4 at
 * byte 2)": where the reader stopped, in parentheses; a file cut short is PC_ERR_TRUNCATED. */
PC_API pc_status pc_load_memory(const void *data, size_t size, const pc_options *opts,
                                pc_model **model, pc_error *err);
/* Load from a file, which must be a regular file: where there is POSIX, a FIFO, a device or
 * a folder is refused at once (PC_ERR_IO), without waiting for a writer. */
PC_API pc_status pc_load_file(const char *path, const pc_options *opts,
                              pc_model **model, pc_error *err);
PC_API void pc_free(pc_model *model);

/* Loading without malloc, for targets without a heap: the model is built inside the
 * caller's buffer, which must stay alive and untouched while the model is used (pc_free
 * is then a no-op). pc_required_bytes gives the buffer size pc_load_into needs for this
 * file and these options (it allocates; run it on a host or once at start-up). The
 * buffer holds load-time scratch too, so it is larger than pc_arena_bytes: after the
 * call the model occupies only [(char *)model, (char *)model + pc_arena_bytes(model)),
 * at the end of the buffer, and the bytes before it are free for the caller again. */
PC_API pc_status pc_required_bytes(const void *data, size_t size, const pc_options *opts,
                                   size_t *bytes, pc_error *err);
PC_API pc_status pc_load_into(const void *data, size_t size, const pc_options *opts,
                              void *buffer, size_t buffer_size, pc_model **model,
                              pc_error *err);

/* Corrects n poses: in and out hold n*7 floats and are the same array or do not overlap
 * (a partial overlap is PC_ERR_ARGUMENT: a later pose would be read after an earlier one
 * was written over it). n == 0 is a no-op.
 * Checks, the same for every model whoever wrote it, each with a message naming the pose
 * and column and what was expected (pc_model_message); the input is checked whole before
 * anything is written (with pc_run_timed the times first, every pose's, then the poses),
 * and a pose's first broken clause, in this order, is reported:
 *  - a non-finite input value: PC_ERR_NONFINITE, out untouched;
 *  - an input quaternion whose norm is off 1 by more than 1e-3, the pose tables'
 *    tolerance (the model normalises what it gets, so a zero or a norm-3 vector would come
 *    out as a made-up rotation): PC_ERR_QUATERNION, out untouched;
 *  - a position outside the model's metadata "input_bounds" ("[[x_lo, y_lo, z_lo],
 *    [x_hi, y_hi, z_hi]]", metres; posecorr's exporter writes the training positions'
 *    box, widened): PC_ERR_RANGE, out untouched;
 *  - a result that is not finite, whose quaternion is not unit within 2e-3 on |q|^2 (the
 *    input rule: a position-only model passes the input's quaternion through), or
 *    that moves the pose farther than the metadata "correction_reach" ("[metres,
 *    radians]": the largest correction of position and of rotation the exporter saw on
 *    the training data, with a margin): PC_ERR_RUNTIME; poses of earlier chunks (of
 *    max_batch, ..., 16, 1 poses) are written, the rest untouched.
 * Loading refuses a file whose metadata "model_digest" does not match its bytes
 * (PC_ERR_INTEGRITY), a graph whose rows are not independent (PC_ERR_GRAPH: probe poses
 * run as one batch and one by one must agree within 1e-5, relative; a probe finds a graph
 * that mixes rows, it proves nothing of one whose mixing the probes do not show, such as
 * one that adds a batch sum and takes it away again), and (PC_ERR_MALFORMED) a float
 * tensor of the graph holding NaN or infinity, and "input_bounds", "time_bounds" or
 * "correction_reach" that are not finite float32 numbers or whose lower bound is above
 * the upper one. A model
 * without "input_bounds" or "correction_reach" loads only with PC_LOAD_ALLOW_UNBOUNDED,
 * one without "model_digest" only with PC_LOAD_ALLOW_UNSIGNED.
 * The message of a pose's refusal reads "pose I: CLAUSE", I the pose's index in this call
 * (0 when n is 1: a caller that runs one pose at a time and names it otherwise, by a line
 * of its input, may show CLAUSE alone), CLAUSE naming a column by the contract's names at
 * the top of this file (x, y, z, qw, qx, qy, qz; t the time), e.g. "pose 3: y = 5.000 m is
 * outside the range the model was fitted on, -0.797 to -0.374 m (metadata input_bounds)". */
PC_API pc_status pc_run(pc_model *model, const float *in, size_t n, float *out);

/* pc_run with the time of each pose: t holds n floats, seconds since the session's start
 * (a non-finite one: PC_ERR_NONFINITE naming the pose; one outside the model's metadata
 * "time_bounds", "[t_lo, t_hi]" in seconds, the span of the training times widened:
 * PC_ERR_RANGE, out untouched). A model without the input "t" ignores t, unchecked. t may be NULL:
 * a model that takes time then sees t = 0 for every pose, i.e. a time-dependent
 * correction (drift) is evaluated at the session's start (and t = 0 is checked against
 * "time_bounds"); pc_run is pc_run_timed with t = NULL. */
PC_API pc_status pc_run_timed(pc_model *model, const float *in, const float *t, size_t n,
                              float *out);

/* 1 when the model has the input "t" (its correction depends on time), else 0. */
PC_API int pc_model_takes_time(const pc_model *model);

/* Context of the last failing pc_run on this model ("" after success). */
PC_API const char *pc_model_message(const pc_model *model);

/* metadata_props of the model, in file order. key/value return NULL out of range. */
PC_API size_t pc_metadata_count(const pc_model *model);
PC_API const char *pc_metadata_key(const pc_model *model, size_t index);
PC_API const char *pc_metadata_value(const pc_model *model, size_t index);
/* Value for key, or NULL when absent. */
PC_API const char *pc_metadata_lookup(const pc_model *model, const char *key);

/* Introspection, mostly for tools and tests. */
PC_API size_t pc_max_batch(const pc_model *model);
PC_API size_t pc_arena_bytes(const pc_model *model);
/* Number of kernel launches for one pose (after folding, aliasing and fusion). */
PC_API size_t pc_step_count(const pc_model *model);
PC_API size_t pc_node_count(const pc_model *model);

/* What a step of the one-pose plan (pc_step_count of them) runs: code written for its shape
 * (a dense chain whose every layer has the kernel of its K and N, a program compiled ahead
 * of time), general code, or the program interpreter. */
typedef enum pc_path {
    PC_PATH_SPECIALISED = 0,
    PC_PATH_GENERAL,
    PC_PATH_INTERPRETED,
    PC_PATH_COUNT
} pc_path;
/* "specialised", "general", "interpreted" (never NULL). */
PC_API const char *pc_path_name(pc_path path);
/* The path of step `step` in *path and, in the caller's buffer why[why_size] (truncated to
 * fit; why may be NULL with why_size 0), what the step is and why it runs that path, e.g.
 * "dense chain 9-10-10-9: every layer runs the kernel of its K and N". PC_ERR_ARGUMENT for
 * a NULL model or path, or step >= pc_step_count(model). */
PC_API pc_status pc_model_step_path(const pc_model *model, size_t step, pc_path *path,
                                    char *why, size_t why_size);

#ifdef __cplusplus
}
#endif
#endif /* POSECORR_H */
