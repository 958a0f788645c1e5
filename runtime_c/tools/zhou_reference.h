/* A hand-written C implementation of the shipped zhou MLP
 * (models/mlp-zhou-tansig-20x20x20x20-br.onnx: quaternion -> rotation matrix -> 6D (Zhou)
 * encoding, input scaling, 9-20-20-20-20-9 tansig network, output scaling, Gram-Schmidt
 * decoding -> unit quaternion with qw >= 0), the reference posecorr-bench times pc_run
 * against (--reference-zhou). It does, in float32 and in the same order, what the
 * exported graph does, with the runtime's own tanh, so its output equals pc_run's. */
#ifndef PC_ZHOU_REFERENCE_H
#define PC_ZHOU_REFERENCE_H

#include <stddef.h>

#define PC_ZHOU_IN 9
#define PC_ZHOU_HIDDEN 20
#define PC_ZHOU_LAYERS 5

/* The weights, in this order, as float32 in a file (runtime_c/tools/zhou_weights.py
 * writes it from the .onnx file). W is [in][out] (Gemm without transposes). */
typedef struct pc_zhou_weights {
    float in_scale[PC_ZHOU_IN], in_offset[PC_ZHOU_IN];
    float w_in[PC_ZHOU_IN * PC_ZHOU_HIDDEN], b_in[PC_ZHOU_HIDDEN];
    float w_hidden[PC_ZHOU_LAYERS - 2][PC_ZHOU_HIDDEN * PC_ZHOU_HIDDEN];
    float b_hidden[PC_ZHOU_LAYERS - 2][PC_ZHOU_HIDDEN];
    float w_out[PC_ZHOU_HIDDEN * PC_ZHOU_IN], b_out[PC_ZHOU_IN];
    float out_scale[PC_ZHOU_IN], out_offset[PC_ZHOU_IN];
} pc_zhou_weights;

#define PC_ZHOU_FLOATS (sizeof(pc_zhou_weights) / sizeof(float))

/* One pose in (x, y, z, qw, qx, qy, qz), one corrected pose out. */
void pc_zhou_reference(const pc_zhou_weights *w, const float *in, float *out);

/* Its three parts, so that another network implementation (the firmware's emlearn
 * comparison) runs between the same encode and decode: the pose -> the network's scaled
 * input x[9]; the network's output y[9] -> scaled back and decoded into a pose. */
void pc_zhou_encode(const pc_zhou_weights *w, const float *in, float *x);
void pc_zhou_network(const pc_zhou_weights *w, const float *x, float *y);
void pc_zhou_decode(const pc_zhou_weights *w, const float *y, float *out);

#endif
