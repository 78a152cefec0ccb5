"""deckland_interfaces message types for rosbags, read from their ``.msg`` files (pure).

rosbags' Jazzy typestore knows the standard types only. :func:`register` adds deckland's own
from the same ``.msg`` text rosidl generated the rclpy classes from, so rosbags serialises them
to the same CDR, and a bag written through the typestore carries their ``ros2msg``
definitions and RIHS01 hashes. The files are looked up in the installed package (each
``AMENT_PREFIX_PATH`` prefix, then this interpreter's prefix) and, failing that, in the source
tree beside this package.
"""

from __future__ import annotations

import os
from pathlib import Path
import sys
from typing import Any

PACKAGE = 'deckland_interfaces'

#: ``src/deckland_interfaces/msg`` of the source tree this module sits in (editable install).
SOURCE_MSG_DIR = Path(__file__).resolve().parents[3] / PACKAGE / 'msg'


def candidate_dirs(env: dict[str, str] | None = None) -> list[Path]:
    """Where the ``.msg`` files may be, in order: ``<prefix>/share/deckland_interfaces/msg``
    for each ``AMENT_PREFIX_PATH`` prefix and ``sys.prefix``, then the source tree."""
    env = os.environ if env is None else env
    prefixes = [p for p in env.get('AMENT_PREFIX_PATH', '').split(os.pathsep) if p]
    prefixes.append(sys.prefix)
    dirs = [Path(p) / 'share' / PACKAGE / 'msg' for p in prefixes]
    dirs.append(SOURCE_MSG_DIR)
    return dirs


def find_msg_dir(env: dict[str, str] | None = None) -> Path | None:
    """The first candidate directory holding ``.msg`` files, ``None`` if there is none."""
    for path in candidate_dirs(env):
        if path.is_dir() and any(path.glob('*.msg')):
            return path
    return None


def definitions(msg_dir: str | os.PathLike[str] | None = None) -> dict[str, str]:
    """``{'deckland_interfaces/msg/Name': .msg text}`` of every message in ``msg_dir`` (default
    :func:`find_msg_dir`), sorted by name; empty when no directory is found."""
    path = Path(msg_dir) if msg_dir is not None else find_msg_dir()
    if path is None:
        return {}
    return {f'{PACKAGE}/msg/{f.stem}': f.read_text(encoding='utf-8')
            for f in sorted(path.glob('*.msg'))}


def parse(defs: dict[str, str]) -> dict[str, Any]:
    """rosbags type dict (name -> (constants, fields)) of the ``.msg`` texts of ``defs``."""
    from rosbags.typesys import get_types_from_msg

    types: dict[str, Any] = {}
    for name, text in defs.items():
        types.update(get_types_from_msg(text, name))
    return types


def register(store: Any, msg_dir: str | os.PathLike[str] | None = None) -> list[str]:
    """Add the deckland_interfaces messages to the rosbags typestore ``store``.

    Idempotent (a type already registered with the same definition is accepted; a different
    one raises rosbags' ``TypesysError``). Returns the names registered, sorted; an empty list
    when no ``.msg`` files are found (the package is not built and no source tree is here).
    """
    types = parse(definitions(msg_dir))
    if types:
        store.register(types)
    return sorted(types)


def typestore() -> Any:
    """A fresh Jazzy typestore with the deckland_interfaces messages registered."""
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS2_JAZZY)
    register(store)
    return store
