/* Layer 3, ONNX decoding: ModelProto, GraphProto, NodeProto, ValueInfoProto, TensorProto
 * and AttributeProto, with their field numbers named in one place, into the graph IR. */
#ifndef PC_ONNX_H
#define PC_ONNX_H

#include "ir.h"

/* Field numbers from onnx.proto (only those the runtime reads). */
enum { ONNX_MODEL_GRAPH = 7, ONNX_MODEL_OPSET_IMPORT = 8, ONNX_MODEL_METADATA_PROPS = 14 };
enum { ONNX_OPSET_DOMAIN = 1, ONNX_OPSET_VERSION = 2 };
enum { ONNX_STRING_KEY = 1, ONNX_STRING_VALUE = 2 };
enum {
    ONNX_GRAPH_NODE = 1,
    ONNX_GRAPH_INITIALIZER = 5,
    ONNX_GRAPH_INPUT = 11,
    ONNX_GRAPH_OUTPUT = 12,
    ONNX_GRAPH_SPARSE_INITIALIZER = 15
};
enum {
    ONNX_NODE_INPUT = 1,
    ONNX_NODE_OUTPUT = 2,
    ONNX_NODE_NAME = 3,
    ONNX_NODE_OP_TYPE = 4,
    ONNX_NODE_ATTRIBUTE = 5,
    ONNX_NODE_DOC_STRING = 6,
    ONNX_NODE_DOMAIN = 7
};
enum {
    ONNX_ATTR_NAME = 1,
    ONNX_ATTR_F = 2,
    ONNX_ATTR_I = 3,
    ONNX_ATTR_T = 5,
    ONNX_ATTR_FLOATS = 7,
    ONNX_ATTR_INTS = 8
};
enum {
    ONNX_TENSOR_DIMS = 1,
    ONNX_TENSOR_DATA_TYPE = 2,
    ONNX_TENSOR_FLOAT_DATA = 4,
    ONNX_TENSOR_INT32_DATA = 5,
    ONNX_TENSOR_INT64_DATA = 7,
    ONNX_TENSOR_NAME = 8,
    ONNX_TENSOR_RAW_DATA = 9,
    ONNX_TENSOR_DATA_LOCATION = 14
};
/* ValueInfoProto.name/type, TypeProto.tensor_type, TypeProto.Tensor.elem_type/shape,
 * TensorShapeProto.dim, Dimension.dim_value. */
enum { ONNX_VALUE_INFO_NAME = 1, ONNX_VALUE_INFO_TYPE = 2 };
enum { ONNX_TYPE_TENSOR = 1, ONNX_TENSOR_TYPE_ELEM = 1, ONNX_TENSOR_TYPE_SHAPE = 2 };
enum { ONNX_SHAPE_DIM = 1, ONNX_DIM_VALUE = 1 };
/* TensorProto.DataType values the runtime reads. */
enum { ONNX_FLOAT = 1, ONNX_INT32 = 6, ONNX_INT64 = 7, ONNX_BOOL = 9 };
/* TensorProto.DataLocation EXTERNAL */
enum { ONNX_EXTERNAL = 1 };

/* One decoded AttributeProto; repeated fields stay in msg for onnx_attr_repeated. */
typedef struct onnx_attr {
    pb_slice msg;
    int has_f, has_i, has_t;
    float f;
    int64_t i;
    pb_slice t;
} onnx_attr;

/* Finds attribute `name` of node n. */
pc_status onnx_attr_find(const pc_builder *b, const pc_node *n, const char *name,
                         onnx_attr *a, int *found);
/* Elements of repeated field `number` (ONNX_ATTR_FLOATS or ONNX_ATTR_INTS). */
pc_status onnx_attr_repeated(const pc_builder *b, const onnx_attr *a, uint32_t number,
                             int64_t *ints, float *floats, size_t cap, size_t *n);
/* A TensorProto as a new constant value. */
pc_status onnx_tensor_to_const(pc_builder *b, pb_slice tensor, int32_t *id);
/* The whole file into b: opset, metadata, nodes, initializers, inputs and outputs. */
pc_status onnx_parse_model(pc_builder *b);

#endif
