"""Where noisestop keeps what a user calibrates or trains: never inside the installed package.

`noisestop calibrate` and `noisestop pretrain` write, unless given `--out`, to the user
data directory, and the readers look there before the files that ship with the package.
Precedence, for each file (flip's calibration `flip.json`, the pre-trained conv weights
`weights/pretrained.safetensors`):

1. an explicit path (`--out` when writing; a path argument or `--calibration` / weights
   path when reading),
2. the user data directory,
3. the file shipped with the package.

The user data directory is `$NOISESTOP_DATA_DIR` if set, else `$XDG_DATA_HOME/noisestop`,
else `~/.local/share/noisestop` (the XDG rule on every platform: platformdirs is not a
dependency, and using it only when some other package happened to install it would move
the directory under the user's feet). Only the maintainer flag `--update-package` of `calibrate`,
`pretrain` and `train` writes the shipped files (the Makefile's `model` target uses it).
"""
from __future__ import annotations

import os
from pathlib import Path

ENV = "NOISESTOP_DATA_DIR"
#: the flag that writes the shipped files instead of the user's
UPDATE_PACKAGE = "--update-package"


def user_data_dir() -> Path:
    """The user data directory (not created here; see the module's docstring for the order)."""
    explicit = os.environ.get(ENV)
    if explicit:
        return Path(explicit).expanduser()
    xdg = os.environ.get("XDG_DATA_HOME")
    # the XDG rule: a relative path is invalid and is ignored
    base = Path(xdg) if xdg and os.path.isabs(xdg) else Path.home() / ".local" / "share"
    return base / "noisestop"


def user_file(name: str) -> Path:
    """`name` (a path relative to the data directory) in the user data directory."""
    return user_data_dir() / name


def find(name: str, shipped: Path) -> Path:
    """The user's `name` if it exists, else the shipped file (which may not exist either).

    Parameters
    ----------
    name : str
        Path relative to the user data directory, e.g. ``"flip.json"``.
    shipped : pathlib.Path
        The file the package ships.

    Returns
    -------
    pathlib.Path
        The file a reader without an explicit path should use.
    """
    mine = user_file(name)
    # anything there (a link to a device included) is the user's: its reader refuses what is
    # not a regular file, rather than the shipped file being used without a word
    return mine if mine.exists() or mine.is_symlink() else shipped
