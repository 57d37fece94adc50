"""Exception hierarchy of mems-stereo.

Input errors subclass :class:`ValueError` so callers that already catch
``ValueError`` keep working; the CLI turns every :class:`MemsStereoError` into
a one-line message on stderr and a non-zero exit code, without a traceback.
"""

from __future__ import annotations


class MemsStereoError(Exception):
    """Base class of every error the package raises on purpose.

    Examples
    --------
    >>> try:
    ...     ms.preset("no-such-preset")
    ... except ms.MemsStereoError as err:       # any error the package raises on purpose
    ...     print("caught", type(err).__name__)  # doctest: +ELLIPSIS
    caught Unknown...Error
    """


class FormatError(MemsStereoError, ValueError):
    """A file or an in-memory description does not follow FORMAT v1.

    Parameters
    ----------
    message : str
        What was expected and what was found.
    source : str, optional
        The file (or ``"<dict>"``) the bad value came from.
    field : str, optional
        Dotted path of the bad field (``"receiver.camera_matrix"``) or the HDF5
        dataset (``"/shots/bins"``).

    Examples
    --------
    >>> try:
    ...     ms.data.path("rom.h5")
    ... except ms.FormatError as err:
    ...     print(err.field, isinstance(err, ValueError))
    mems_stereo.data.path True
    """

    def __init__(self, message: str, source: str | None = None, field: str | None = None):
        self.source = source
        self.field = field
        self.reason = message
        parts = []
        if source:
            parts.append(str(source))
        if field:
            parts.append(field)
        prefix = ": ".join(parts)
        super().__init__(f"{prefix}: {message}" if prefix else message)


class GeometryError(MemsStereoError, ValueError):
    """Geometric input that cannot be used (degenerate basis, wrong shape...).

    Examples
    --------
    >>> issubclass(ms.GeometryError, ValueError), issubclass(ms.GeometryError, ms.MemsStereoError)
    (True, True)
    """


class NotObservableError(MemsStereoError):
    """A calibration parameter the data cannot determine.

    Examples
    --------
    >>> issubclass(ms.NotObservableError, ms.MemsStereoError)
    True
    """


class ShapeError(FormatError, GeometryError):
    """An array of the wrong shape or dtype (in memory or in a file).

    The one exception of this kind of fault wherever it is detected; it
    subclasses both :class:`FormatError` and :class:`GeometryError` so that
    code catching either (the classes used for it before version 0.2) keeps
    working.
    """


class OptionError(FormatError):
    """A command-line option or API argument out of its range; ``field`` names it."""


class UnsafeFileError(FormatError):
    """A file that would make the package read outside it: HDF5 external storage,
    external links, virtual datasets, mesh paths outside the scene's folder."""


class ResourceError(MemsStereoError, ValueError):
    """An input whose claimed sizes exceed the file's real size or the memory budget
    (``--max-memory``, :func:`mems_stereo.util.limits.max_memory`)."""


class UnknownNameError(MemsStereoError, KeyError):
    """An unknown name (system parameter, preset); also a :class:`KeyError`."""

    def __str__(self) -> str:  # KeyError would quote the message
        return str(self.args[0]) if self.args else ""
