/* A hand-written C implementation of a posecorr tanh MLP: the pose encoded (quaternion ->
 * rotation matrix -> its first two columns for the 6D (zhou) representation, or the
 * canonical quaternion, through the same matrix, for quat), the input scaling, a chain of
 * dense layers with tanh between them, the output scaling, and the decoding (Gram-Schmidt
 * for zhou, the canonical quaternion for quat) into a unit quaternion with qw >= 0. It does,
 * in float32 and in the same order, what the exported graph does, with the runtime's own
 * tanh, so its output equals pc_run's. posecorr-bench times pc_run against it on the
 * shipped zhou 20-20-20-20 (--reference-zhou); the embedded firmwares on any such MLP
 * (embed.py weights writes the model's weights as a pc_mlp). */
#ifndef PC_ZHOU_REFERENCE_H
#define PC_ZHOU_REFERENCE_H

#include <stddef.h>

/* The network's input and output width per encoding, and the widest layer it supports. */
#define PC_ZHOU_IN 9
#define PC_QUAT_IN 7
#define PC_MLP_MAX_WIDTH 32

typedef enum pc_mlp_encoding { PC_MLP_ZHOU, PC_MLP_QUAT } pc_mlp_encoding;

/* One dense layer act(x W + b), W [k][n] (Gemm without transposes); tanh on all but the last. */
typedef struct pc_mlp_layer {
    size_t k, n;
    const float *w, *b;
} pc_mlp_layer;

typedef struct pc_mlp {
    pc_mlp_encoding encoding;
    size_t layers;
    const pc_mlp_layer *layer;
    const float *in_scale, *in_offset, *out_scale, *out_offset;
} pc_mlp;

/* The network's input and output width: PC_ZHOU_IN or PC_QUAT_IN. */
size_t pc_mlp_width(const pc_mlp *m);
/* One pose in (x, y, z, qw, qx, qy, qz), one corrected pose out. */
void pc_mlp_reference(const pc_mlp *m, const float *in, float *out);
/* Its three parts, so that another network implementation (the firmware's emlearn
 * comparison) runs between the same encode and decode: the pose -> the network's scaled
 * input x[width]; the network's output y[width] -> scaled back and decoded into a pose. */
void pc_mlp_encode(const pc_mlp *m, const float *in, float *x);
void pc_mlp_network(const pc_mlp *m, const float *x, float *y);
void pc_mlp_decode(const pc_mlp *m, const float *y, float *out);

/* The shipped zhou MLP 9-20-20-20-20-9 as the float32 file posecorr-bench --reference-zhou
 * reads (runtime_c/tools/zhou_weights.py writes it from the .onnx file), in this order. */
#define PC_ZHOU_HIDDEN 20
#define PC_ZHOU_LAYERS 5
typedef struct pc_zhou_weights {
    float in_scale[PC_ZHOU_IN], in_offset[PC_ZHOU_IN];
    float w_in[PC_ZHOU_IN * PC_ZHOU_HIDDEN], b_in[PC_ZHOU_HIDDEN];
    float w_hidden[PC_ZHOU_LAYERS - 2][PC_ZHOU_HIDDEN * PC_ZHOU_HIDDEN];
    float b_hidden[PC_ZHOU_LAYERS - 2][PC_ZHOU_HIDDEN];
    float w_out[PC_ZHOU_HIDDEN * PC_ZHOU_IN], b_out[PC_ZHOU_IN];
    float out_scale[PC_ZHOU_IN], out_offset[PC_ZHOU_IN];
} pc_zhou_weights;

#define PC_ZHOU_FLOATS (sizeof(pc_zhou_weights) / sizeof(float))

/* m (with its layers in `layer`) describing w, which must outlive them. */
void pc_zhou_describe(const pc_zhou_weights *w, pc_mlp_layer layer[PC_ZHOU_LAYERS], pc_mlp *m);

#endif
