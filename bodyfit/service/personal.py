"""A request's subject file (``subject=``): the one place where synthesis, scan and sequence fits and
upgrades turn it into the known person's body (:class:`FixedBody`: their decoder and their shape, held
fixed), and where a subject that cannot be used, or one that contradicts the request, is refused."""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np
import torch

from bodyfit.io.npz import DAMAGED
from bodyfit.models.body.model import BodyDecoder, BodyModel
from bodyfit.models.fitting.registered.fitter import FixedBody
from bodyfit.models.rig.subject import Subject, SubjectError
from bodyfit.service.errors import InvalidInputError

SUBJECT_FIELD = "subject"
REBUILD = "build one for this server's model with `bodyfit rig` or POST /v1/subjects"


def read_subject(model: BodyModel, data: bytes | Subject) -> Subject:
    """The subject file ``data`` (the ``.npz`` bytes of ``bodyfit rig``, or a :class:`Subject`) checked
    against ``model`` (format, sha256, the model's fingerprint, array sizes).

    Raises:
        InvalidInputError: an empty upload, not a subject file, a damaged or altered one, or one built for
            another body model (field ``subject``; the message says how to get a usable one).
    """
    if isinstance(data, Subject):
        try:
            data.check_model(model)
        except SubjectError as exc:
            raise InvalidInputError(str(exc), SUBJECT_FIELD) from None
        return data
    if not data:
        raise InvalidInputError(f"the subject file is empty; send a subject .npz ({REBUILD})", SUBJECT_FIELD)
    try:
        return Subject.from_bytes(bytes(data), model)
    except SubjectError as exc:
        raise InvalidInputError(str(exc), SUBJECT_FIELD) from None
    except (*DAMAGED, KeyError) as exc:
        # a truncated archive or one without a subject's arrays, which the reader does not name itself
        raise InvalidInputError(
            f"not a usable subject file (a damaged or incomplete .npz: {exc}); {REBUILD}", SUBJECT_FIELD
        ) from None


def personal_body(model: BodyModel, subject: bytes | Subject | None) -> FixedBody | None:
    """The known person of a request's subject file (:func:`read_subject`), or None without one: their shape
    (n_shape,) and their decoder per float type (:meth:`Subject.decoder`, built once each per request)."""
    if subject is None:
        return None
    person = read_subject(model, subject)
    built: dict[torch.dtype, BodyDecoder] = {}

    def decoders(dtype: torch.dtype) -> BodyDecoder:
        if dtype not in built:
            built[dtype] = person.decoder(model, dtype)
        return built[dtype]

    return FixedBody(np.asarray(person.shape, np.float64), decoders)


def check_alone(body: FixedBody | None, given: Iterable[tuple[str, object]]) -> None:
    """Refuse a subject sent together with a request field that also says what the body is like (shape
    coefficients, measurements, shape hints): the subject's body has its own shape.

    Args:
        given: (field name, value) pairs; a value of None is a field not sent.
    Raises:
        InvalidInputError: naming the first such field and which one to drop.
    """
    if body is None:
        return
    for name, value in given:
        if value is not None:
            raise InvalidInputError(
                f"give a subject or {name}, not both: the subject's body has its own shape; drop {name} to "
                f"use the subject, or drop the subject to use {name}",
                name,
            )
