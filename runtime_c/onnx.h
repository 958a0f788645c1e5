/* Layer 3, ONNX decoding: ModelProto, GraphProto, NodeProto, ValueInfoProto, TensorProto
 * and AttributeProto, with their field numbers named in one place. Nothing is decoded
 * ahead: the scan and the planner ask for one message at a time. */
#ifndef PC_ONNX_H
#define PC_ONNX_H

#include "ir.h"

/* printf arguments of a name: "%.*s" */
#define PC_NAME(s) (int)(s).size, (const char *)(s).data

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

/* A TensorProto: type, shape and where its data is. */
typedef struct onnx_tensor {
    int64_t dims[PC_MAX_RANK];
    size_t rank, count, n_float, n_int32, n_int64;
    int64_t data_type;
    int dtype;          /* the runtime's type (int32 data is held as int64) */
    pb_slice name, raw;
    int has_raw;
} onnx_tensor;

/* ModelProto: opset, graph and the checks of the top level into b. */
pc_status onnx_scan_model(pc_builder *b);
/* metadata_props in file order: call with *r initialised on the whole file (pb_init);
 * returns PB_FIELD with key and value, PB_END, or PB_ERROR (r->status). */
int onnx_next_meta(const pc_builder *b, pb_reader *r, pb_slice *key, pb_slice *value);
/* The next NodeProto of the graph (r initialised on b->graph), as onnx_next_meta. */
int onnx_next_node(const pc_builder *b, pb_reader *r, pb_slice *msg);
/* Counts of the graph's repeated fields; checks their wire types. */
pc_status onnx_graph_counts(pc_builder *b, uint32_t *nodes, uint32_t *inits, size_t *io);
/* The node in msg into n (lists on the work end of the scratch). */
pc_status onnx_parse_node(pc_builder *b, pb_slice msg, uint32_t index, pc_node *n);
/* Graph inputs (without initializers listed among them) and outputs, checked against the
 * contract (or, any_io, against static shapes), into b->inputs and b->outputs (keep end).
 * Output refs are left for the scan. */
pc_status onnx_parse_io(pc_builder *b, size_t n_io);
/* Type, shape and payload of a TensorProto, checked against each other. */
pc_status onnx_tensor_header(const pc_builder *b, pb_slice msg, onnx_tensor *t);
/* The tensor's contents in the runtime's type: where they lie in the file when that is
 * possible (little-endian raw float32 or int64, aligned), else decoded into fresh scratch
 * on the given end. */
pc_status onnx_tensor_data(pc_builder *b, pb_slice msg, const onnx_tensor *t, int end,
                           void **data);
/* Finds attribute `name` of node n. */
pc_status onnx_attr_find(const pc_builder *b, const pc_node *n, const char *name,
                         onnx_attr *a, int *found);
/* Elements of repeated field `number` (ONNX_ATTR_FLOATS or ONNX_ATTR_INTS). */
pc_status onnx_attr_repeated(const pc_builder *b, const onnx_attr *a, uint32_t number,
                             int64_t *ints, float *floats, size_t cap, size_t *n);

#endif
