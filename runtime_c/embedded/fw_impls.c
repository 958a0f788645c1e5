/* See fw_impls.h. */
#include "fw_impls.h"

#include "mlp_weights.h"
#include "zhou_reference.h"

int fw_hand(const float in[7], float out[7])
{
    pc_mlp_reference(&pc_fw_mlp, in, out);
    return 0;
}

#ifdef FW_EMLEARN
#include "eml_net.h"

/* The MLP's layers in emlearn's structures, over the same weights (emlearn reads W[i][o]
 * at o + i * n_outputs, the exporter's layout), between the same encode and decode; its
 * two activation buffers as wide as the widest layer. */
static float eml_buffer1[PC_FW_MLP_WIDTH], eml_buffer2[PC_FW_MLP_WIDTH];
static EmlNetLayer eml_layers[PC_FW_MLP_LAYERS];
static EmlNet eml_model = {PC_FW_MLP_LAYERS, eml_layers, eml_buffer1, eml_buffer2, PC_FW_MLP_WIDTH};

void fw_emlearn_setup(void)
{
    size_t l;
    for (l = 0; l < PC_FW_MLP_LAYERS; l++) {
        const pc_mlp_layer *p = &pc_fw_mlp.layer[l];
        eml_layers[l] = (EmlNetLayer){(int32_t)p->n, (int32_t)p->k, p->w, p->b,
                                      l + 1 < PC_FW_MLP_LAYERS ? EmlNetActivationTanh
                                                               : EmlNetActivationIdentity};
    }
}

int fw_emlearn(const float in[7], float out[7])
{
    float x[PC_ZHOU_IN], y[PC_ZHOU_IN];
    const int32_t width = (int32_t)pc_mlp_width(&pc_fw_mlp);
    pc_mlp_encode(&pc_fw_mlp, in, x);
    if (eml_net_regress(&eml_model, x, width, y, width) != EmlOk)
        return 1;
    pc_mlp_decode(&pc_fw_mlp, y, out);
    return 0;
}
#endif
