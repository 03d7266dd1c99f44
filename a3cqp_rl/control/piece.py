"""What tasks and limits share: a name, whether they run on numpy contexts, and their C translation hook."""

from __future__ import annotations


class QPPiece:
    """Base of `Task` and `Limit`: one term of the controller's QP."""

    name: str = "piece"
    numpy_capable: bool = False
    """True when the piece also runs on a context of numpy arrays (arrays.py); the controller's CPU step uses numpy
    only when every task and limit is (a piece written with torch calls keeps working: that step runs on torch)."""

    def c_params(self) -> tuple[str, dict] | None:
        """(kind, its fields of the native step's parameters, control/native) or None when C does not translate it.

        Only a class that defines `_c_params` itself is translated: a subclass may change the math."""
        own = type(self).__dict__.get("_c_params")
        return None if own is None else own(self)
