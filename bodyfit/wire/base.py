"""The base of every wire document."""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict


class WireModel(BaseModel):
    """A document of the wire contract: immutable; keys it does not declare are ignored when read (a newer
    server may add some), except in the open documents that keep them (:class:`OpenDocument`)."""

    model_config = ConfigDict(frozen=True, extra="ignore")


class OpenDocument(WireModel):
    """A document whose set of keys may grow (a fit's report, a sequence's statistics, an upgrade's
    summary): keys it does not declare are kept, and written back out, as they came."""

    model_config = ConfigDict(extra="allow")
