/* The hand-written function and emlearn's eml_net of the firmware's MLP (fw_impls.c, over
 * the pc_mlp that embed.py weights writes into mlp_weights.h), for the instruction counts
 * of small.c and compiled.c. Each returns 0 when it corrected the pose. */
#ifndef PC_EMBEDDED_FW_IMPLS_H
#define PC_EMBEDDED_FW_IMPLS_H

int fw_hand(const float in[7], float out[7]);
#ifdef FW_EMLEARN
/* Fills emlearn's layer structures once, before fw_emlearn. */
void fw_emlearn_setup(void);
int fw_emlearn(const float in[7], float out[7]);
#endif

#endif
