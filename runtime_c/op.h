/* Layer 5, operators: one prepare function per ONNX operator (pc_op_<Name>, in the file
 * of its family), which checks input types, infers output shapes, picks a kernel with its
 * parameter block and says how a one-pose program computes each output element; plus the
 * helpers those functions share (op.c). The table of operators is generated from
 * export/operators.txt. */
#ifndef PC_OP_H
#define PC_OP_H

#include "kernels.h"
#include "onnx.h"

/* How a one-pose program computes the output's elements (program.c), declared by the
 * operator's prepare function; NONE keeps the kernel. */
typedef enum pc_emap {
    PC_EMAP_NONE = 0,
    PC_EMAP_SOP,      /* elementwise: sop of the broadcast inputs (Where: cond, then, else) */
    PC_EMAP_SELECT,   /* a copy of an input element: pc_prep.select says which */
    PC_EMAP_SUM,      /* the sum of each innermost block (pc_reduce, d[5] terms) */
    PC_EMAP_PRODUCT   /* act(A B + C), the sums of pc_gemm in its kernel's order */
} pc_emap;

typedef struct pc_prep pc_prep;
/* Output element e copies element *elem of input *input. */
typedef void (*pc_select_fn)(const pc_prep *p, size_t e, size_t *input, size_t *elem);

/* One node being prepared for one plan (or for constant folding). */
struct pc_prep {
    pc_builder *b;
    pc_node *node;
    size_t n_in, n_out;
    int32_t *in_ids;    /* records (pc_builder.values); -1 for an omitted input */
    int32_t *out_ids;
    pc_value **in;      /* NULL for an omitted optional input */
    pc_value **out;
    pc_kernel_fn fn;
    void *prm;
    size_t prm_size;
    int32_t alias_of;   /* output 0 is a view of this record (no kernel) */
    int emap;           /* pc_emap */
    int sop;            /* PC_EMAP_SOP: the element operation (PC_SOP_*, kernels.h) */
    pc_select_fn select;/* PC_EMAP_SELECT */
    int layer;          /* an MLP layer (rows of act(A B + c)) that may chain with the next */
    int folding;
};

typedef pc_status (*pc_prepare_fn)(pc_prep *p);

enum {
#define PC_OP(name) PC_OP_##name,
#include "pc_operators.def"
#undef PC_OP
    PC_OP_COUNT
};

/* Every operator of operators.txt must have its prepare function somewhere. */
#define PC_OP(name) pc_status pc_op_##name(pc_prep *p);
#include "pc_operators.def"
#undef PC_OP

typedef struct pc_op_info {
    const char *name;
    pc_prepare_fn prepare;
} pc_op_info;

extern const pc_op_info pc_ops[PC_OP_COUNT];
int pc_op_lookup(pb_slice name);

/* Prepares node n whose inputs and outputs are the records in_ids and out_ids (n->n_in
 * and n->n_out of them; -1 for an omitted one): fills p (kernel, parameters, output
 * shapes, element map) or fails naming the node. */
pc_status pc_prepare_node(pc_builder *b, pc_node *n, const int32_t *in_ids,
                          const int32_t *out_ids, int folding, pc_prep *p);

/* Helpers for the prepare functions. */
pc_status pc_prep_fail(pc_prep *p, pc_status st, const char *fmt, ...)
#ifdef __GNUC__
    __attribute__((format(printf, 3, 4)))
#endif
    ;
pc_status pc_attr_int(pc_prep *p, const char *name, int64_t def, int64_t *out);
pc_status pc_attr_float(pc_prep *p, const char *name, float def, float *out);
pc_status pc_attr_ints(pc_prep *p, const char *name, int64_t *buf, size_t cap, size_t *n,
                       int *found);
pc_status pc_attr_floats(pc_prep *p, const char *name, float *buf, size_t cap, size_t *n,
                         int *found);
pc_status pc_attr_tensor(pc_prep *p, const char *name, pb_slice *tensor, int *found);
/* Bytes of attribute `name`'s message (0 when absent): no repeated field in it holds more
 * elements, so a buffer of that many elements takes them all. */
size_t pc_attr_bytes(pc_prep *p, const char *name);
int pc_has_attr(pc_prep *p, const char *name);
pc_status pc_input_ints(pc_prep *p, size_t k, int64_t *buf, size_t cap, size_t *n);
pc_status pc_input_float_scalar(pc_prep *p, size_t k, float *out);
pc_status pc_set_out(pc_prep *p, size_t k, int dtype, int rank, const int64_t *dims);
/* Output k with the shape of `like`. */
pc_status pc_set_out_as(pc_prep *p, size_t k, int dtype, const pc_value *like);
void *pc_prep_params(pc_prep *p, size_t size);
/* A constant record of the node's own (Constant's value), its data on the work end. */
pc_status pc_new_const(pc_prep *p, int dtype, int rank, const int64_t *dims, void **data,
                       int32_t *id);
/* Pads the operand list with omitted inputs up to n, for a kernel that finds its output
 * after n input slots. */
pc_status pc_pad_inputs(pc_prep *p, size_t n);
/* Axes from input 1 (opset 13) or the attribute (older exporters). */
pc_status pc_axes(pc_prep *p, int64_t *axes, size_t *n, int *given);
/* axis in [-rank, rank) to [0, rank). */
pc_status pc_norm_axis(pc_prep *p, int64_t *axis, int rank);

#endif
