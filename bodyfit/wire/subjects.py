"""``POST /v1/subjects``: a personal rig built from several scans of one person; the server keeps nothing,
the answer carries the portable subject file."""

from __future__ import annotations

from typing import Annotated

from pydantic import Field, TypeAdapter

from bodyfit.wire.arrays import Base64Bytes
from bodyfit.wire.base import WireModel
from bodyfit.wire.events import ErrorEvent, ProgressEvent, _ResultTag


class SubjectResult(WireModel):
    """The rig of one person: the scans it was built from (names as uploaded), each one's mean vertex error
    (mm) under the generic model and under the rig, the limb joints the poses left undetermined (built
    anyway when allowed; from the shape space), the build's seconds, and ``subject``: the subject file
    (an ``.npz``; base64 in JSON) that synthesis and fits take back."""

    scans: tuple[str, ...]
    generic_mm: tuple[float, ...]
    personal_mm: tuple[float, ...]
    undetermined_joints: tuple[str, ...]
    seconds: float
    subject: Base64Bytes


class SubjectResultEvent(SubjectResult, _ResultTag):
    """The result event of a rig build."""


SubjectEvent = Annotated[ProgressEvent | SubjectResultEvent | ErrorEvent, Field(discriminator="event")]
"""An event of ``POST /v1/subjects``."""
SUBJECT_EVENTS: TypeAdapter[ProgressEvent | SubjectResultEvent | ErrorEvent] = TypeAdapter(SubjectEvent)
