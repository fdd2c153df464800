"""Exceptions raised by the library.

Every error that comes from user input names the file (and line, where there is one) and says what
is wrong, so a failed run can be fixed without reading a traceback.
"""

from __future__ import annotations

from pathlib import Path


class AtlasError(Exception):
    """Base class of every error the library raises on purpose."""


class ConfigError(AtlasError):
    """A configuration profile or the dataset registry is invalid."""


class DatasetError(AtlasError):
    """Input data (list files, images, ground truth) is missing or malformed.

    Attributes:
        path: the offending file or folder.
        line: 1-based line number inside ``path``, when the problem is on one line.
    """

    def __init__(self, path: str | Path, message: str, line: int | None = None):
        self.path = Path(path)
        self.line = line
        where = f"{self.path}:{line}" if line is not None else f"{self.path}"
        super().__init__(f"{where}: {message}")


class BundleFormatError(AtlasError):
    """A saved world (PLY, ATLASGS binary, metadata) cannot be read."""

    def __init__(self, path: str | Path, message: str):
        self.path = Path(path)
        super().__init__(f"{self.path}: {message}")


class ArtifactError(AtlasError):
    """An artifact written by an earlier stage is missing or does not match its record."""


class OutputPolicyError(AtlasError):
    """An output path may not be replaced (a user's folder, an input of the same command, a link)."""

    def __init__(self, path: str | Path, message: str):
        self.path = Path(path)
        super().__init__(f"{self.path}: {message}")


class WriteError(AtlasError):
    """Writing an output failed (read-only folder, full disk ...); names the path."""

    def __init__(self, path: str | Path, message: str, errno_: int | None = None):
        self.path = Path(path)
        self.errno = errno_
        super().__init__(f"{self.path}: {message}")
