"""Where the data folders `objects/` and `lists/` live.

A wheel carries them inside the package as `geo_server/_data/{objects,lists}` (see
`pyproject.toml`); an editable install or a plain checkout finds them at the repository
root next to `geo_server/`. Both are tried, installed copy first.
"""

from __future__ import annotations

from pathlib import Path

_PACKAGE = Path(__file__).resolve().parent
#: The data folder of an installed wheel (absent in a checkout / editable install).
PACKAGED_DATA = _PACKAGE / "_data"


def data_dir(name: str) -> Path:
    """Return the folder `objects` or `lists`, wherever this installation keeps it."""
    for candidate in (_PACKAGE / "_data" / name, _PACKAGE.parent / name):
        if candidate.is_dir():
            return candidate
    raise FileNotFoundError(
        f"geo-server data folder {name!r} not found (looked in {_PACKAGE / '_data'} "
        f"and {_PACKAGE.parent}); reinstall the package"
    )


def default_startup_list() -> Path:
    """The default machine's start-up list `lists/hochlauf.lis`."""
    return data_dir("lists") / "hochlauf.lis"


def is_packaged_data(path: str | Path) -> bool:
    """True for a file inside an installed wheel's data folder (site-packages), which
    `save` must not edit: an upgrade would overwrite it and other users share it."""
    try:
        Path(path).resolve().relative_to(PACKAGED_DATA)
    except ValueError:
        return False
    return True
