/*
 * posecorr.h - the one public header of libposecorr.
 *
 * libposecorr loads a posecorr corrector (.onnx, opset 13..21, the operator subset of
 * export/operators.txt) and applies it to tracker poses:
 *
 *     input  "pose"      float32 [N,7] = x, y, z, qw, qx, qy, qz
 *     output "corrected" float32 [N,7]
 *
 * Everything the model needs at run time lives in one arena allocated by pc_load_*;
 * pc_run never allocates, never blocks and touches no global state, so one model may be
 * run from one thread at a time and different models from different threads.
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
#define PC_VERSION_MINOR 1
#define PC_VERSION_PATCH 0

/* Poses are 7 floats: x, y, z, qw, qx, qy, qz. */
#define PC_POSE_WIDTH 7
/* Default and upper bound of pc_options.max_batch. */
#define PC_DEFAULT_MAX_BATCH 256
#define PC_MAX_MAX_BATCH 4096
#define PC_MESSAGE_SIZE 256

typedef enum pc_status {
    PC_OK = 0,
    PC_ERR_ARGUMENT,       /* NULL pointer or out-of-range argument */
    PC_ERR_IO,             /* file cannot be opened or read */
    PC_ERR_MEMORY,         /* allocation failed at load */
    PC_ERR_TRUNCATED,      /* protobuf message ends inside a field */
    PC_ERR_MALFORMED,      /* protobuf is not valid wire format / ONNX structure */
    PC_ERR_UNSUPPORTED,    /* operator, attribute, data type or opset not supported */
    PC_ERR_CONTRACT,       /* not "pose" float32 [N,7] -> "corrected" float32 [N,7] */
    PC_ERR_GRAPH,          /* dangling input, cycle, duplicate output, ... */
    PC_ERR_SHAPE,          /* shapes or types of a node do not fit together */
    PC_ERR_NONFINITE,      /* NaN or infinity in an input pose */
    PC_ERR_RUNTIME,        /* data-dependent failure, e.g. Gather index out of range */
    PC_STATUS_COUNT
} pc_status;

/* Static description of a status code (never NULL). */
PC_API const char *pc_status_name(pc_status status);

typedef struct pc_error {
    pc_status status;
    char message[PC_MESSAGE_SIZE];
} pc_error;

typedef struct pc_options {
    /* Largest number of poses evaluated at once; rounded down to a power of two.
     * 0 selects PC_DEFAULT_MAX_BATCH. pc_run handles any n by chunking (plans exist
     * for 1, 16, 256, ... poses and max_batch). */
    size_t max_batch;
} pc_options;

typedef struct pc_model pc_model;

/* Load from a buffer; the buffer may be freed once the call returns. opts may be NULL;
 * err may be NULL. On failure *model is NULL. */
PC_API pc_status pc_load_memory(const void *data, size_t size, const pc_options *opts,
                                pc_model **model, pc_error *err);
PC_API pc_status pc_load_file(const char *path, const pc_options *opts,
                              pc_model **model, pc_error *err);
PC_API void pc_free(pc_model *model);

/* Corrects n poses: in and out hold n*7 floats and may alias. n == 0 is a no-op.
 * A non-finite input value gives PC_ERR_NONFINITE and leaves out untouched. */
PC_API pc_status pc_run(pc_model *model, const float *in, size_t n, float *out);

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

#ifdef __cplusplus
}
#endif
#endif /* POSECORR_H */
