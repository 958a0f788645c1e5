/* Layer 4, operators: one prepare function per ONNX operator (pc_op_<Name>, in the file
 * of its family), which checks input types, infers output shapes and picks a kernel with
 * its parameter block; plus the helpers those functions share (op.c). The table of
 * operators is generated from export/operators.txt. */
#ifndef PC_OP_H
#define PC_OP_H

#include "kernels.h"
#include "onnx.h"

/* One node being prepared for one plan (or for constant folding). */
typedef struct pc_prep {
    pc_builder *b;
    pc_node *node;
    size_t n_in, n_out;
    int32_t *in_ids;    /* may be replaced by derived constants */
    int32_t *out_ids;
    pc_value **in;      /* NULL for an omitted optional input */
    pc_value **out;
    pc_kernel_fn fn;
    void *prm;
    size_t prm_size;
    int32_t alias_of;   /* output 0 is a view of this value (no kernel) */
    int sop;            /* float elementwise meaning (PC_SOP_*, kernels.h), 0 for others:
                         * what a one-pose program runs in place of the kernel */
    int folding;
} pc_prep;

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

/* Kinds of constants the operators derive from an input (cached across plans). */
enum { PC_DERIVED_TRANSPOSE = 1, PC_DERIVED_GATHER = 2 };

/* Prepares node n: fills p (kernel, parameters, output shapes) or fails naming it. */
pc_status pc_prepare_node(pc_builder *b, pc_node *n, int folding, pc_prep *p);

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
int pc_has_attr(pc_prep *p, const char *name);
pc_status pc_input_ints(pc_prep *p, size_t k, int64_t *buf, size_t cap, size_t *n);
pc_status pc_input_float_scalar(pc_prep *p, size_t k, float *out);
pc_status pc_set_out(pc_prep *p, size_t k, int dtype, int rank, const int64_t *dims);
void *pc_prep_params(pc_prep *p, size_t size);
pc_status pc_new_const(pc_prep *p, int dtype, int rank, const int64_t *dims, void **data,
                       int32_t *id);
/* Axes from input 1 (opset 13) or the attribute (older exporters). */
pc_status pc_axes(pc_prep *p, int64_t *axes, size_t *n, int *given);
/* axis in [-rank, rank) to [0, rank). */
pc_status pc_norm_axis(pc_prep *p, int64_t *axis, int rank);

/* Float comparison kernels per layout (op_elementwise.c), bool output. */
extern const pc_kernel_fn k_eq_f[PC_LAYOUTS], k_gt_f[PC_LAYOUTS], k_ge_f[PC_LAYOUTS],
    k_lt_f[PC_LAYOUTS], k_le_f[PC_LAYOUTS];

#endif
