"""Writes the fuzz seed corpus: every test graph of graphs.py as a .onnx file."""
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import graphs  # noqa: E402

out = Path(sys.argv[1])
out.mkdir(parents=True, exist_ok=True)
n = 0
for name, build in sorted(graphs.op_cases().items()):
    for k, m in enumerate(build()):
        (out / f"{name}_{k}.onnx").write_bytes(m.SerializeToString())
        n += 1
(out / "pose.onnx").write_bytes(graphs.pose_model(hidden=(8, 8)).SerializeToString())
print(f"{n + 1} seeds in {out}")
