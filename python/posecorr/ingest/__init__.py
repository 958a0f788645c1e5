"""From a recording (ROS 1/2 bag, MCAP, CSV log) to the paired-pose table: `posecorr ingest`."""
from __future__ import annotations

from .pipeline import IngestOptions, IngestResult, ingest, segments_path, write_segments
from .streams import IngestError, JointStream, PoseStream

__all__ = ["IngestError", "IngestOptions", "IngestResult", "JointStream", "PoseStream", "ingest",
           "segments_path", "write_segments"]
