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
#: A source checkout's root and its data folders (`data_dir` looks there second).
CHECKOUT = _PACKAGE.parent
CHECKOUT_DATA = ("lists", "objects")


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
    """True for a file inside an installed wheel's data folder (site-packages): an
    upgrade would overwrite it and other users share it."""
    return _below(path, PACKAGED_DATA)


def is_product_data(path: str | Path) -> bool:
    """True for a file of the shipped data — the default machine, the object dictionary —
    wherever it comes from: an installed wheel's data folder or the `lists/` and
    `objects/` folders beside a source checkout, whose files are tracked and read by the
    tests. `save` never edits one (docs/design.md §4.5: `geo-server init DIR` copies the
    default machine to a folder of the user's)."""
    return is_packaged_data(path) or any(_below(path, CHECKOUT / name) for name in CHECKOUT_DATA)


def _below(path: str | Path, folder: Path) -> bool:
    try:
        Path(path).resolve().relative_to(folder.resolve())
    except ValueError:
        return False
    return True
