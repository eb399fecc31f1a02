"""How snapshots travel on SQLite (:mod:`.storage`): files in the data directory.

``snapshots/f<id>-s<seq>.snap`` is a field's snapshot file; the parts it names
(an atlas field's charts, :meth:`flatserve.contract.SampledField.write_parts`)
are ``snapshots/parts/p<id>-<key>``, each stored once whatever the number of
snapshots naming it: a snapshot after a batch that touched one chart writes
that chart's part and a small file. Every file is written under a temporary
name, fsync'd, renamed into place and its directory fsync'd before the
database points the field at the snapshot (:mod:`.sqlrules`); then the former
snapshot file goes, then the field's parts the new one does not name.

A reader of a snapshot replaced meanwhile finds its file gone and is told so
(:class:`~.rows.SnapshotGoneError`: it reads the new one). A field's writer
holds the field's snapshot lease (:func:`~.backend.snapshot_lease`: one writer
of a field at a time; different fields' writers run at once). Every file a
writer makes carries its field's id: the snapshot under
``snapshots/.tmp-f<id>-s<seq>.snap-<pid>-<thread>``, new parts in
``snapshots/parts/.stage-f<id>-<pid>-<thread>-<random>`` until moved into place
(a part stored by itself: ``.stage-f<id>-<pid>-<random>-<key>``), so that
:meth:`~.backend.LogBackend.clean_orphans` removes what a writer that died left
of a field under that field's lease only, never another field's writer's files;
the files of fields that are gone, and those of no field, at once.
"""
from __future__ import annotations

import logging
import os
import shutil
import threading
import uuid
from pathlib import Path
from typing import Callable, TypeVar

from ...errors import SnapshotError
from .rows import FieldRow, SnapshotInfo
from .datadir import fsync_path
from .sqlrules import snapshot_failure, snapshot_name
from ..status import StorageError

log = logging.getLogger("flatserve.service")

T = TypeVar("T")

#: Prefix of a writer's directory of new parts under ``snapshots/parts``
#: (followed by ``f<field id>-``).
STAGE_PREFIX = ".stage-"
#: Prefix of a snapshot file being written (followed by its final name).
TMP_PREFIX = ".tmp-"


def part_name(field_id: int, key: str) -> str:
    """The file name of field ``field_id``'s part ``key``."""
    return f"p{field_id}-{key}"


class SnapshotFiles:
    """:meth:`LogBackend.write_snapshot`, ``load_snapshot``, ``snapshot_parts``,
    ``snapshot_bytes`` and the hooks of ``clean_orphans`` of
    :class:`~.storage.SQLiteBackend`, with the rulebook's snapshot hooks
    (state: ``snapshot_dir``, ``parts_dir``)."""

    snapshot_dir: Path
    parts_dir: Path

    def snapshot_path(self, file: str) -> Path:
        return self.snapshot_dir / file

    def part_path(self, field_id: int, key: str) -> Path:
        return self.parts_dir / part_name(field_id, key)

    def snapshot_parts(self, field_id: int) -> set[str]:
        prefix = part_name(field_id, "")
        try:
            return {p.name[len(prefix):] for p in self.parts_dir.iterdir()
                    if p.name.startswith(prefix)}
        except OSError as exc:
            raise StorageError(f"cannot list the snapshot parts in {self.parts_dir}: "
                               f"{exc}") from exc

    def store_part(self, field_id: int, key: str, data: bytes) -> int:
        """Written under a temporary name, fsync'd, renamed into place, the
        directory fsync'd."""
        final = self.part_path(field_id, key)
        if final.is_file():
            return 0
        tmp = self.parts_dir / (f"{STAGE_PREFIX}f{field_id}-{os.getpid()}-"
                                f"{uuid.uuid4().hex[:8]}-{key}")
        try:
            with open(tmp, "wb") as out:
                out.write(data)
                out.flush()
                os.fsync(out.fileno())
            os.replace(tmp, final)
            fsync_path(self.parts_dir)
        except OSError as exc:
            tmp.unlink(missing_ok=True)
            raise snapshot_failure(exc) from exc
        return len(data)

    def remove_parts(self, field_id: int, keys) -> None:
        for key in keys:
            try:
                self.part_path(field_id, key).unlink(missing_ok=True)
            except OSError as exc:
                raise StorageError(f"cannot remove {self.part_path(field_id, key)}: "
                                   f"{exc}") from exc

    def write_snapshot(self, field_id: int, seq: int, position: int,
                       save: Callable[[Path, Path], list[str] | None],
                       check: Callable[[], None] | None = None) -> SnapshotInfo:
        """Write a snapshot file and its new parts atomically (temporary names,
        fsync, rename, fsync of the directories), then point the field at it
        (:mod:`.sqlrules`)."""
        name = f"f{field_id}-s{seq}.snap"
        final = self.snapshot_dir / name
        tag = f"{os.getpid()}-{threading.get_ident()}"
        tmp = self.snapshot_dir / f"{TMP_PREFIX}{name}-{tag}"
        stage = self.parts_dir / f"{STAGE_PREFIX}f{field_id}-{tag}-{uuid.uuid4().hex[:8]}"
        try:
            stage.mkdir()
            keys = list(save(tmp, stage) or [])
            if not tmp.exists():  # a writer that appended an extension
                cands = list(self.snapshot_dir.glob(tmp.name + ".*"))
                if len(cands) != 1:
                    raise StorageError(f"snapshot writer did not create {tmp}")
                tmp = cands[0]
            fsync_path(tmp)
            size = tmp.stat().st_size
            new = [p for p in stage.iterdir()]
            for p in new:  # (each fsync'd by its writer)
                size += p.stat().st_size
                os.replace(p, self.part_path(field_id, p.name))
            if new:
                fsync_path(self.parts_dir)
            if check is not None:  # before the rename: a lost lease leaves the old file be
                check()
            os.replace(tmp, final)
            fsync_path(self.snapshot_dir)
        except OSError as exc:
            tmp.unlink(missing_ok=True)
            raise snapshot_failure(exc) from exc
        except BaseException:
            tmp.unlink(missing_ok=True)
            raise
        finally:
            shutil.rmtree(stage, ignore_errors=True)
        return SnapshotInfo(name, size, self._point(field_id, name, seq, position, None, keys))

    def _forget_snapshot(self, db, field_id: int, name: str | None) -> list[str]:
        return [name] if name else []  # the file goes after the commit (then the parts)

    def _snapshot_stored(self, db, name: str) -> bool:
        return self.snapshot_path(name).is_file()

    def _parts_stored(self, db, field_id: int, keys: list[str]) -> bool:
        return all(self.part_path(field_id, k).is_file() for k in keys)

    def _discard_snapshots(self, names: list[str]) -> None:
        for file in names:
            try:
                self.snapshot_path(file).unlink(missing_ok=True)
            except OSError as exc:  # pragma: no cover - best effort
                log.warning("could not remove snapshot %s: %s", file, exc)

    def _discard_parts(self, field_id: int, keep: list[str]) -> None:
        try:
            stale = self.snapshot_parts(field_id) - set(keep)
        except StorageError as exc:  # pragma: no cover - best effort
            log.warning("%s", exc)
            return
        self._discard_snapshots([f"parts/{part_name(field_id, k)}" for k in sorted(stale)])

    def read_part(self, field_id: int, key: str) -> bytes:
        path = self.part_path(field_id, key)
        try:
            return path.read_bytes()
        except FileNotFoundError:
            raise SnapshotError(f"snapshot part {key} of field id {field_id} is missing "
                                f"({path})") from None
        except OSError as exc:  # unreadable here: damaged, as for the snapshot's file
            raise SnapshotError(f"snapshot part {key} of field id {field_id}: cannot read "
                                f"{path}: {exc}") from exc

    def load_snapshot(self, row: FieldRow, load: Callable[[Path, Callable[[str], bytes]], T]) -> T:
        return self.load_with_parts(row, self.snapshot_path(row.snapshot_file), load)

    def snapshot_location(self, row: FieldRow) -> str:
        return str(self.snapshot_path(row.snapshot_file))

    def snapshot_bytes(self, row) -> int:
        """The snapshot file's size plus its field's parts' (those a snapshot
        names, and a former one's until they are removed)."""
        file = snapshot_name(row)
        if not file:
            return 0
        try:
            size = self.snapshot_path(file).stat().st_size
        except OSError:
            return 0
        field_id = row.id if isinstance(row, FieldRow) else _field_id(file)
        if field_id is None:
            return size
        for key in self.snapshot_parts(field_id):
            try:
                size += self.part_path(field_id, key).stat().st_size
            except OSError:
                pass
        return size

    def _leftovers(self) -> tuple[dict[int, list[Path]], list[Path]]:
        """What no field points at: ``(by live field id, of no live field)``. The
        files of a live field are its snapshot files but the one it points at,
        a writer's temporary files and staging directories (never its parts: the
        next snapshot removes those no snapshot names); of no live field, all
        of a field that is gone (and files of no field). The directories are
        listed before the fields are read: a writer's file listed belongs to a
        field created before, so a field missing then was deleted (ids are
        never reused)."""
        found: list[tuple[int | None, Path, bool]] = []  # (field id, path, is a part)
        for p in self.snapshot_dir.iterdir():
            if p.is_file() and not p.is_symlink():  # (never a directory mounted there)
                found.append((_owner_id(p.name), p, False))
        for p in self.parts_dir.iterdir():
            if p.is_symlink():
                continue
            if p.name.startswith(STAGE_PREFIX) and (p.is_dir() or p.is_file()):
                found.append((_owner_id(p.name), p, False))
            elif p.is_file():
                found.append((_field_id(p.name, prefix="p"), p, True))
        pointed = {f.id: f.snapshot_file for f in self.fields()}
        live: dict[int, list[Path]] = {}
        gone: list[Path] = []
        for fid, p, part in found:
            if fid is None or fid not in pointed:
                gone.append(p)
            elif not part and p.name != pointed[fid]:
                live.setdefault(fid, []).append(p)
        return live, gone

    def _orphan_fields(self) -> set[int]:
        return set(self._leftovers()[0])

    def _clean_orphans(self, field_id: int | None) -> int:
        live, gone = self._leftovers()
        doomed = gone if field_id is None else live.get(field_id, [])
        for p in doomed:
            if p.is_dir():
                shutil.rmtree(p, ignore_errors=True)
            else:
                p.unlink(missing_ok=True)
        return len(doomed)


def _owner_id(name: str) -> int | None:
    """The field id of a file in ``snapshots`` or a writer's staging entry
    (``f<id>-s<seq>.snap``, ``.tmp-f<id>-...``, ``.stage-f<id>-...``); None: of
    no field (one of an earlier version, or not flatserve's)."""
    for prefix in (TMP_PREFIX, STAGE_PREFIX):
        if name.startswith(prefix):
            return _field_id(name[len(prefix):])
    return _field_id(name)


def _field_id(name: str, prefix: str = "f") -> int | None:
    """The field id in ``f<id>-s<seq>.snap`` (or ``p<id>-<key>``); None if not one."""
    head = name.split("-", 1)[0]
    if head[:1] != prefix or not head[1:].isdigit():
        return None
    return int(head[1:])
