"""Message schemas, one module per stream.

``STREAMS`` maps each stream name to its message class. See ``_codec`` for the wire format
and ``*.json`` beside this file for the machine-readable descriptions (regenerate them with
``python -m gaitflow.schemas``).
"""

from gaitflow.schemas._codec import (
    REGISTRY,
    Header,
    Message,
    decode,
    decode_any,
    encode,
    json_schema,
    messages_equal,
    peek_header,
)
from gaitflow.schemas.blobs import Blobs
from gaitflow.schemas.calibration import CalibrationRecord, CalibrationStatus
from gaitflow.schemas.clean import CleanFrame
from gaitflow.schemas.gait import GaitFrame, TrialSummary
from gaitflow.schemas.labelled import LabelledMarkers
from gaitflow.schemas.markers import Markers3D
from gaitflow.schemas.model import SubjectModel
from gaitflow.schemas.raw import RawFrame
from gaitflow.schemas.truth import GroundTruth

STREAMS = REGISTRY

__all__ = [
    "STREAMS",
    "Blobs",
    "CalibrationRecord",
    "CalibrationStatus",
    "CleanFrame",
    "GaitFrame",
    "GroundTruth",
    "Header",
    "LabelledMarkers",
    "Markers3D",
    "Message",
    "RawFrame",
    "SubjectModel",
    "TrialSummary",
    "decode",
    "decode_any",
    "encode",
    "json_schema",
    "messages_equal",
    "peek_header",
]
