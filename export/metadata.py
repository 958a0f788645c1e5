"""The `metadata_props` of an exported model (docs/design.md, "The ONNX contract").

Every value is stored as a string; anything that is not already a string (numbers, lists,
dicts, None) is JSON-encoded, and `posecorr.controller.onnx_meta.read_info` decodes it back.

Keys written by the exporter (other keys may be added by callers):

| key | value |
|---|---|
| `posecorr_version` | version of the package that exported the model |
| `method` | `pmc`, `mlp`, `none`, ... |
| `representation` | the core's input: `eaa`, `quat`, `R`, `zhou` or `pos` (position only); null without a core |
| `architecture` | text: the hidden layer sizes, e.g. `20-20` (MLP), or the PMC feature layout |
| `activation`, `trainer` | MLP activation and training algorithm (null for PMC) |
| `effects` | fitted physical-effect stages in front of the core, with their parameters |
| `effect_behaviour` | (effects an `--effect-file` defines) the trial poses after each such effect at its fitted values (`posecorr.effects.behaviour`): another file's effect of the same name is told apart |
| `station_pose` | (a physics stage fitted with `--station-pose`) `{"stated": the option's text, "reference": [x, y, z, qw, qx, qy, qz]}`: where the base station was taken to stand, in the reference frame; `report` and `diagnose` take it as their default |
| `training_data_digest` | `sha256:<hex>` of the training arrays, see `data_digest` |
| `training_set_digest` | `sha256:<hex>` of the same rows in any order, see `set_digest` (models exported before it was added state none) |
| `fitted_table_digest` | (`fit` with a test split) the same digest of the whole table it split |
| `fitted_table_set_digest` | (`fit` with a test split) that table's rows in any order, see `set_digest` |
| `test_metrics` | rmse_pos (m), rmse_rot (rad), rmse_total and improvements on the held-out poses; "raw"; "rigid": the best rigid fit scored alike (fit) |
| `units` | units of the input/output columns and the metrics |
| `opset` | ONNX opset of the default domain |
| `parity` | float32 graph vs float64 `predict`: max errors and the check's settings |
| `input_bounds` | `[[x_lo, y_lo, z_lo], [x_hi, y_hi, z_hi]]` (m): the training positions' box, widened; every runtime refuses a pose outside it |
| `time_bounds` | `[t_lo, t_hi]` (s), models with the time input `t`: the training times' span, widened; a time outside is refused |
| `correction_reach` | `[metres, radians]`: the largest correction of position and rotation on the training poses and on poses of any orientation drawn inside `input_bounds`, with a margin (`onnx_export.REACH_*`); every runtime refuses a pose corrected farther |
| `training_orientations` | (a core that reads the orientation) `{"mean": [qw, qx, qy, qz], "within": rad}`: the training orientations' mean and the largest angle of any from it (`posecorr.coverage`); no runtime checks it, `apply` counts the poses beyond it |
| `model_digest` | `crc32c:<8 hex>`: CRC-32C of the file's bytes with these 8 digits read as `00000000` (`posecorr.controller.digest`); every loader verifies it |
"""
from __future__ import annotations

import json
from typing import Any, Mapping

import numpy as np

from posecorr.controller.digest import data_digest

UNITS = {
    "pose": ("x, y, z in m; qw, qx, qy, qz unit quaternion, scalar first; measured in the frame of the "
             "tracker data the model was fitted on, corrected in the reference's frame (the robot base)"),
    "rmse_pos": "m", "rmse_rot": "rad", "rmse_total": "m + rad (w_pos = 1/m, w_rot = 1)",
}


def _jsonable(value: Any) -> Any:
    if isinstance(value, Mapping):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if isinstance(value, np.ndarray):
        return _jsonable(value.tolist())
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, float) and not np.isfinite(value):
        return None if np.isnan(value) else ("inf" if value > 0 else "-inf")
    return value


def encode_value(value: Any) -> str:
    """A metadata value as the string stored in the model."""
    if isinstance(value, str):
        return value
    return json.dumps(_jsonable(value), sort_keys=True, allow_nan=False)


def encode_metadata(metadata: Mapping[str, Any]) -> dict[str, str]:
    """All values as strings, keys sorted (deterministic files)."""
    return {str(k): encode_value(v) for k, v in sorted(metadata.items())}
