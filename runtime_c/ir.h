/* Layer 2, graph IR: the model under construction (values, nodes, names), filled by the
 * ONNX decoder and transformed by the passes, the operators and the planner. */
#ifndef PC_IR_H
#define PC_IR_H

#include "pb.h"
#include "scratch.h"

typedef enum pc_dtype {
    PC_F32 = 1,
    PC_I64 = 7,
    PC_BOOL = 9
} pc_dtype;

size_t pc_dtype_size(int dtype);
const char *pc_dtype_name(int dtype);

typedef struct pc_value {
    pb_slice name;
    int dtype;          /* 0 until known */
    int rank;
    int64_t dims[PC_MAX_RANK];
    size_t count;
    void *cdata;        /* constant contents (scratch), NULL for run-time values */
    int producer;       /* node index, -1 for graph input / initializer */
    int consumers;      /* live, unfolded consumers (+1 for a graph output) */
    /* planner bookkeeping, per plan */
    int32_t alias;      /* value whose storage this one shares, or -1 */
    int32_t def, last;  /* step index of definition and last use */
    size_t offset;      /* offset in the activation region */
    int32_t const_slot; /* -1 until placed in the constant region */
    size_t const_offset;
} pc_value;

typedef struct pc_node {
    pb_slice name, op_type, domain;
    int op;
    uint32_t n_in, n_out, n_attr;
    int32_t *in;        /* value ids, -1 for an omitted optional input */
    int32_t *out;
    pb_slice *attr;     /* AttributeProto messages, decoded on demand */
    pb_slice *in_names, *out_names;
    int live, folded, fused_away;
    int act;            /* pc_act (kernels.h) fused into this node */
    float act_lo, act_hi;
} pc_node;

typedef struct pc_meta {
    pb_slice key, value;
} pc_meta;

/* A graph input or output: value id and declared type (inputs: the shape they get). */
typedef struct pc_io {
    pb_slice name;
    int32_t id;
    int dtype;
    int rank;
    int64_t dims[PC_MAX_RANK];
} pc_io;

/* A constant the operators derived from another (a transposed weight, ...), kept once
 * for all plans. */
typedef struct pc_derived {
    int32_t src;
    int kind;
    int32_t id;
} pc_derived;

typedef struct pc_builder {
    pc_scratch scratch;
    pc_error *err;
    const uint8_t *file;
    size_t file_size;
    int64_t opset;
    /* 0: the pose contract (one input 'pose' [N,7], one output 'corrected'); 1: any
     * named inputs and outputs of static shape (the ONNX conformance tests only). */
    int any_io;
    pc_node *nodes;
    size_t n_nodes;
    pc_value *values;
    size_t n_values, cap_values;
    int32_t *order;     /* topological order of nodes */
    pc_meta *meta;
    size_t n_meta;
    int32_t *hash;      /* name -> value id, open addressing */
    size_t hash_cap;
    pc_io *inputs, *outputs;
    size_t n_inputs, n_outputs;
    pc_derived *derived;
    size_t n_derived, cap_derived;
    int cpu_avx2;       /* -1 until asked */
} pc_builder;

/* Room for cap values and their names. */
pc_status pc_ir_reserve(pc_builder *b, size_t cap);
int32_t pc_lookup(const pc_builder *b, pb_slice name);
pc_status pc_new_value(pc_builder *b, pb_slice name, int32_t *id);
/* A constant value with zeroed contents of the given type and shape. */
pc_status pc_alloc_const(pc_builder *b, pb_slice name, int dtype, int rank,
                         const int64_t *dims, int32_t *id);
int32_t pc_find_derived(const pc_builder *b, int32_t src, int kind);
pc_status pc_add_derived(pc_builder *b, int32_t src, int kind, int32_t id);
int pc_is_output(const pc_builder *b, int32_t id);

#endif
