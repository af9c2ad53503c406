"""One exception tree for the core; the edges translate it (API -> 4xx, workers -> job failure)."""

from __future__ import annotations


class CsrError(Exception):
    """Base of every error raised by ``csr_core``."""


class UploadError(CsrError):
    """A trip upload is not acceptable.

    ``location`` names where, as a JSON path such as ``frames[12].gnss.lat``; ``reason`` is a
    short machine-readable code (``schema``, ``non_finite``, ``time_order``, ``version``,
    ``json``); the message says what is wrong in words.
    """

    def __init__(self, message: str, *, location: str = "", reason: str = "schema") -> None:
        super().__init__(message)
        self.message = message
        self.location = location
        self.reason = reason

    def as_dict(self) -> dict[str, str]:
        return {"error": self.reason, "location": self.location, "message": self.message}


class ScenarioError(CsrError):
    """A scenario folder (contract section 5) is missing files or malformed."""


class ReconstructionError(CsrError):
    """A pipeline stage cannot produce a result for its input (degenerate geometry etc.)."""


class AlignmentFailed(ReconstructionError):
    """A trip could not be aligned; ``reason`` says why (kept on the trip as its failure)."""

    def __init__(self, message: str, *, reason: str) -> None:
        super().__init__(message)
        self.reason = reason
