/* Layer 2, the model under load: one decoded node at a time, the records of the values a
 * plan pass holds (only those alive at the node being planned: a graph of hundreds of
 * nodes holds a few dozen at once), and the compact arrays the graph scan leaves for the
 * passes (who reads what, until when). Filled by the ONNX decoder and the scan, read by
 * the operators and the planner. */
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

/* A node input as the scan resolved it: kind in the top two bits, index below. The
 * outputs of all nodes are numbered in file order ("ordinals"). */
enum { PC_REF_NONE = 0, PC_REF_OUTPUT = 1, PC_REF_INIT = 2, PC_REF_INPUT = 3 };
#define PC_REF(kind, index) ((uint16_t)((unsigned)(kind) << 14 | (unsigned)(index)))
#define PC_REF_KIND(r) ((unsigned)(r) >> 14)
#define PC_REF_INDEX(r) ((unsigned)(r) & 0x3fffu)
#define PC_MAX_INDEX 0x3fffu
/* last_use of an output nothing reads, and of one the graph returns. */
#define PC_USE_NONE 0xffffu
#define PC_USE_FOREVER 0xfffeu
#define PC_MAX_NODES 0xfff0u

/* A value of a plan pass (or of the scan's folding): its type and shape, where it is. */
typedef struct pc_value {
    int dtype;          /* 0 until known */
    int rank;
    int32_t dims[PC_MAX_RANK]; /* a dimension is at most PC_MAX_ELEMENTS < 2^31 */
    size_t count;
    void *cdata;        /* constant contents, NULL for run-time values */
    int32_t ckey;       /* constants: placement key (pc_const_key), -1 for none */
    int32_t ordinal;    /* the node output it is, -1 otherwise */
    uint16_t last;      /* index of the last node reading it, or PC_USE_* */
    uint8_t used;       /* the record is taken */
    uint8_t input;      /* a graph input: lives for the whole plan */
    int32_t block;      /* activation block holding it, -1 for none */
    int32_t *elems;     /* one-pose program being built: where each element is */
} pc_value;

/* One NodeProto, decoded for the moment it is looked at. */
typedef struct pc_node {
    pb_slice name, op_type, domain;
    uint32_t index;     /* position in the file */
    int op;
    uint32_t n_in, n_out, n_attr;
    pb_slice *attr;     /* AttributeProto messages, decoded on demand */
    pb_slice *in_names, *out_names;
    int act;            /* pc_act (kernels.h) fused into this node by the scan */
    float act_lo, act_hi;
} pc_node;

/* A graph input or output: declared type and shape, what it is in the graph. */
typedef struct pc_io {
    pb_slice name;
    int dtype;
    int rank;
    int64_t dims[PC_MAX_RANK];
    uint16_t ref;       /* PC_REF_INPUT k, or (outputs) what the graph returns */
} pc_io;

/* A node output the scan folded into a constant. */
typedef struct pc_const pc_const;
struct pc_const {
    pc_const *next;
    uint32_t ordinal;
    int dtype, rank;
    int32_t dims[PC_MAX_RANK];
    size_t count;
    void *data;
};

/* The load: the file, what the scan found, and the records of the current pass. */
typedef struct pc_builder {
    pc_scratch scratch;
    pc_error *err;
    const uint8_t *file;
    size_t file_size;
    int any_io;         /* 0: the pose contract; 1: any names, static shapes (tests) */
    int in_place;       /* the file outlives the model: constants may be used where they lie */
    int64_t opset;
    pb_slice graph;
    /* graph scan (graph.c) */
    uint32_t n_nodes, n_ordinals, n_inits, n_refs;
    uint16_t *node_in0, *node_out0;  /* n_nodes + 1: first ref and first ordinal of a node
                                      * (the scan's only: a pass counts them as it streams) */
    uint16_t *in_ref;                /* every node input, resolved */
    uint16_t *last_use;              /* per ordinal */
    uint8_t *node_op;                /* per node: operator, or PC_NODE_SKIP */
    struct pc_fused *fused;          /* the activations fused into Gemm nodes */
    pb_slice *inits;                 /* TensorProto of each initializer */
    pc_io *inputs, *outputs;
    size_t n_inputs, n_outputs;
    pc_const *consts;                /* folded outputs, newest first */
    size_t max_live;                 /* most records a plan pass holds at once */
    /* plan pass (plan.c): records */
    pc_value *values;
    size_t cap_values;
    size_t values_high;              /* records a pass has taken at once, at most */
    int cpu_avx2;                    /* -1 until asked */
    size_t peak_unplaced;            /* scratch peak before the arena was placed */
} pc_builder;

/* The activation the scan fused into Gemm node `node` (a list: few nodes have one), with
 * a Clip's bounds. */
typedef struct pc_fused {
    struct pc_fused *next;
    uint32_t node;
    int act;
    float lo, hi;
} pc_fused;

/* Scan flags in node_op: the node is skipped by every plan (dead, folded, fused away). */
#define PC_NODE_SKIP 0xffu

/* Placement keys of constants: initializer k is k, the folded output of ordinal o is
 * n_inits + o. */
int32_t pc_key_ordinal(const pc_builder *b, uint32_t ordinal);

/* Records: a free one (zeroed, ids stay valid until released), and its release. */
pc_status pc_value_new(pc_builder *b, int32_t *id);
void pc_value_release(pc_builder *b, int32_t id);
/* A record holding constant data (shape and type given, data owned by the caller). */
pc_status pc_value_const(pc_builder *b, int dtype, int rank, const int64_t *dims, void *data,
                         int32_t key, int32_t *id);
/* The folded output of ordinal o, or NULL. */
const pc_const *pc_const_find(const pc_builder *b, uint32_t ordinal);
/* Adds the folded output of ordinal o, of the type and shape of `like`, with zeroed data
 * on the keep end. */
pc_status pc_const_add(pc_builder *b, uint32_t ordinal, const pc_value *like, pc_const **c);

#endif
