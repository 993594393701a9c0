"""Run checkpoints through ``torchrl.checkpoint``: no pickle on load, checksummed, the
last two kept, the older one used when the newest is damaged."""

from __future__ import annotations

import contextlib
import errno
import hashlib
import json
import os
import shutil
import uuid
import warnings
from collections.abc import Callable
from pathlib import Path

from omegaconf import DictConfig, OmegaConf
from torchrl.checkpoint import Checkpoint, CheckpointAdapter, GlobalRNGState
from torchrl.data import ReplayBuffer

from torchrl_rave.recipe.config import ConfigError
from torchrl_rave.recipe.trust import check_plain_data, check_trusted

__all__ = [
    "CheckpointWriteError",
    "DamagedCheckpoint",
    "DamagedCheckpointWarning",
    "FORMAT_VERSION",
    "RunCheckpoint",
    "RunInUse",
    "UnsafeRunDirectory",
    "UntrustedCheckpoint",
    "check_run_directory",
    "config_for_resume",
    "exclusive_run",
    "missing_checkpoint",
    "read_group_file",
    "saved_config",
]

# written into every manifest's metadata; 3 added checksums.json
FORMAT_VERSION = 3
CHECKSUMS = "checksums.json"
PREFIX = "checkpoint-"
KEEP_LAST = 2
LOCK = ".run.lock"


class CheckpointWriteError(RuntimeError):
    """A checkpoint could not be written (unwritable directory, full disk, ...)."""


class DamagedCheckpoint(RuntimeError):
    """A checkpoint's files do not match the sizes and checksums it was written with."""


class UntrustedCheckpoint(DamagedCheckpoint):
    """A checkpoint holds what torchrl-rave never writes: a file its checksums do not list,
    pickled data, a symbolic link, or a path that leads out of it. Checksums guard against
    damage, not tampering (anyone can rewrite them), so these are refused by kind."""


class UnsafeRunDirectory(ValueError):
    """A run directory holds a symbolic link, through which writing or reading would leave
    the directory."""


class RunInUse(RuntimeError):
    """Another live process is training into the same run directory."""


# what torchrl's checkpoints and tensordict's memory maps are made of; pickles are not
PICKLE_SUFFIXES = (".pickle", ".pkl", ".pt", ".pth", ".bin")


def _inside(name: str) -> bool:
    """Whether a relative path from a file (a checksum entry, a component path) stays below
    the directory it is relative to."""
    parts = Path(name).parts
    return bool(parts) and not Path(name).is_absolute() and ".." not in parts


def check_run_directory(run_dir: str | Path) -> None:
    """Raises :class:`UnsafeRunDirectory` naming the first symbolic link under
    ``run_dir`` that leads outside it (``run_dir`` itself may be one: that is the caller's
    choice). One planted there would make the run's writes (the metric CSVs, the
    checkpoints) or reads land outside the run directory. Links that stay inside are left
    alone, and so is ``wandb/`` (wandb writes it, linking into its own cache, and the run
    neither writes nor reads it); checkpoints hold no links at all."""
    root = Path(run_dir)
    if not root.is_dir():
        return
    inside = root.resolve()
    for dirpath, dirnames, filenames in os.walk(root):  # links are not followed
        if Path(dirpath) == root and "wandb" in dirnames:
            dirnames.remove("wandb")  # wandb's own files, which link into its cache
        for name in dirnames + filenames:
            path = Path(dirpath) / name
            if path.is_symlink() and not path.resolve().is_relative_to(inside):
                raise UnsafeRunDirectory(
                    f"{path} is a symbolic link to {os.readlink(path)}, outside the run "
                    "directory; writing or reading through it would leave the run directory. "
                    "Remove it, or copy the run without links"
                )


@contextlib.contextmanager
def exclusive_run(run_dir: str | Path):
    """Holds ``<run_dir>/.run.lock`` (an exclusive ``flock``) for the block, so that two
    processes never train into, and checkpoint over, one run directory: e.g. a resumed
    run while the one it resumes still runs. Raises :class:`RunInUse` naming the process
    that holds it. The lock goes with its holder: a killed process leaves none behind.
    Where ``fcntl`` does not exist (Windows), the block runs unguarded."""
    try:
        import fcntl
    except ImportError:  # pragma: no cover (not POSIX)
        yield
        return
    if not Path(run_dir).is_dir():
        raise FileNotFoundError(f"{run_dir}: no such run directory")
    check_run_directory(run_dir)
    path = Path(run_dir) / LOCK
    try:  # never through a link planted under the lock's name
        fd = os.open(path, os.O_RDWR | os.O_CREAT | getattr(os, "O_NOFOLLOW", 0), 0o644)
    except OSError as err:
        if err.errno == errno.ELOOP:
            raise UnsafeRunDirectory(f"{path} is a symbolic link; remove it") from None
        raise
    with os.fdopen(fd, "r+") as f:
        try:
            fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            f.seek(0)
            holder = f.read().strip() or "unknown"
            raise RunInUse(
                f"{run_dir} is in use: process {holder} is training into it (it holds "
                f"{path}); stop that process, or wait for it, before resuming the run"
            ) from None
        f.seek(0)
        f.truncate()
        f.write(str(os.getpid()))
        f.flush()
        try:
            yield
        finally:
            f.seek(0)
            f.truncate()
            fcntl.flock(f, fcntl.LOCK_UN)


class DamagedCheckpointWarning(UserWarning):
    """The newest checkpoint was damaged and an older one was used instead."""


class ReplayBufferAdapter(CheckpointAdapter):
    """A replay buffer's storage, sampler and writer, each through its own ``dumps`` /
    ``loads`` (memory maps and JSON). ``ReplayBuffer.dumps`` also pickles its prefetch
    queue, and ``loads`` unpickles it: this adapter writes and reads neither."""

    adapter_id = "torchrl_rave.replay_buffer"

    def save(self, component: ReplayBuffer, path: Path, *, args, kwargs) -> None:
        path.mkdir(parents=True, exist_ok=True)
        if len(component) == 0:  # nothing stored yet (TorchRL cannot dump such a storage)
            (path / "empty.json").write_text('{"size": 0}\n')
            return
        with warnings.catch_warnings():
            # Saved before anything was written since it was loaded (a resumed run stopped
            # during its owed updates), a storage has no last write position, and TorchRL
            # warns that it "may not be saved properly". Only a storage checkpointer's save
            # hooks read that position; without hooks the storage is saved whole.
            if not getattr(component.storage.checkpointer, "_save_hooks", True):
                warnings.filterwarnings("ignore", "last_cursor is None", UserWarning)
            component.storage.dumps(path / "storage")
        component.sampler.dumps(path / "sampler")
        component.writer.dumps(path / "writer")

    def load(self, component: ReplayBuffer, path: Path, **unused) -> None:
        if (path / "empty.json").exists():
            return
        component.storage.loads(path / "storage")
        component.sampler.loads(path / "sampler")
        component.writer.loads(path / "writer")


def _checkpoint(**components) -> Checkpoint:
    return Checkpoint(**components).register_adapter(ReplayBuffer, ReplayBufferAdapter())


def _sha256(path: Path) -> str:
    digest = hashlib.sha256()
    with path.open("rb") as file:
        while chunk := file.read(1 << 20):
            digest.update(chunk)
    return digest.hexdigest()


def _fsync(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _size(path: Path) -> int:
    """The disk space ``path``'s files take: whole blocks, not just their lengths."""
    total = 0
    for f in path.rglob("*"):
        if f.is_file():
            st = f.stat()
            block = max(st.st_blksize, 4096)
            total += max(st.st_blocks * 512, -(-st.st_size // block) * block)
    return total


class RunCheckpoint:
    """The checkpoints of one run: ``<run_dir>/checkpoints/checkpoint-<frames>/``.

    Each is a ``torchrl.checkpoint.Checkpoint`` directory plus ``checksums.json`` (the size
    and SHA-256 of every file). It is written under a hidden name, flushed to disk and
    renamed into place, so a kill at any moment leaves the previous one whole; the two
    newest are kept. Loading checks the checksums first: a damaged newest checkpoint is
    moved to ``checkpoints/damaged/`` and the older one is used, with a
    :class:`~torchrl_rave.recipe.checkpoint.DamagedCheckpointWarning`. Tensors are stored as TensorDict memory maps and
    everything else as JSON: loading one runs no code from it (no pickle).

    The components are the ones passed to :meth:`save` / :meth:`load`: live objects with
    ``state_dict``/``load_state_dict`` (modules, optimisers, the world-model trainer),
    ``dump``/``load`` (the replay buffer) or plain JSON dicts (config, counters), updated
    in place on load; the process's RNG state is always included.

    Why not ``torchrl.checkpoint.CheckpointRotation`` (torchrl 0.14), which keeps the
    newest ``keep_last`` checkpoints of a directory too: it saves straight to the final
    name and records no checksums, so its ``latest()`` / ``load_latest()`` return the
    newest checkpoint whether or not a kill or a full disk damaged it, and its pruning
    keeps a damaged newest one while deleting the older whole one. The rotation here is
    the few lines around that: staging, checksums, the fallback past a damaged checkpoint
    (set aside, not pruned), the free-space check, and refusing what no checkpoint of
    ours holds (links, pickles, unlisted files).
    """

    def __init__(self, run_dir: str | Path) -> None:
        self.root = Path(run_dir) / "checkpoints"

    # ----------------------------------------------------------------------- listing
    def checkpoints(self) -> list[Path]:
        """Every published checkpoint, oldest first (damaged or not)."""
        self._refuse_old_format()
        if not self.root.is_dir():
            return []
        if self.root.is_symlink():
            raise UnsafeRunDirectory(f"{self.root} is a symbolic link; a run directory holds none")
        found = [
            p
            for p in self.root.iterdir()
            if p.name.startswith(PREFIX) and p.name[len(PREFIX) :].isdigit() and p.is_dir()
        ]
        return sorted(found, key=lambda p: int(p.name[len(PREFIX) :]))

    def latest(self) -> Path | None:
        """The newest checkpoint that passes :meth:`verify`, or ``None`` when there is none."""
        return self._newest_valid(None, set_aside=False)

    def verify(self, path: Path, components: list[str] | None = None) -> None:
        """Raises :class:`~torchrl_rave.recipe.checkpoint.DamagedCheckpoint` naming the first file of ``path`` (of the
        given components' files, and the manifest) that is missing, has the wrong size
        or the wrong checksum."""
        path = Path(path)
        try:
            listed = json.loads((path / CHECKSUMS).read_text())["files"]
        except FileNotFoundError:
            raise DamagedCheckpoint(
                f"{path} has no {CHECKSUMS} (written by an interrupted or older torchrl-rave "
                "that kept no checksums)"
            ) from None
        except (ValueError, KeyError, TypeError) as err:
            raise DamagedCheckpoint(f"{path / CHECKSUMS} is unreadable ({err})") from None
        self._refuse_untrusted(path, listed)
        if components is not None:
            try:
                manifest = Checkpoint.manifest(path)
                prefixes = tuple(
                    manifest["components"][name]["path"] + "/"
                    for name in components
                    if name in manifest["components"]
                )
            except Exception as err:  # noqa: BLE001 (any manifest damage is reported)
                raise DamagedCheckpoint(f"{path}/manifest.json is unreadable ({err})") from None
            listed = {
                name: entry
                for name, entry in listed.items()
                if name == "manifest.json" or name.startswith(prefixes)
            }
        for name, (size, sha256) in sorted(listed.items()):
            file = path / name
            if not file.is_file():
                raise DamagedCheckpoint(f"{file} is missing")
            actual = file.stat().st_size
            if actual != size:
                raise DamagedCheckpoint(f"{file} has {actual} bytes, {size} were written")
            if _sha256(file) != sha256:
                raise DamagedCheckpoint(f"{file} does not match its checksum (corrupted)")

    def _refuse_untrusted(self, path: Path, listed: dict) -> None:
        """What no checkpoint of ours holds: links, files outside the checksums, pickles,
        and paths (of checksum entries or manifest components) that leave ``path``."""
        for where in (self.root, path):
            if where.is_symlink():
                raise UntrustedCheckpoint(f"{where} is a symbolic link; a checkpoint holds none")
        for name in listed:
            if not isinstance(name, str) or not _inside(name):
                raise UntrustedCheckpoint(f"{path / CHECKSUMS} lists {name!r}, outside {path}")
        for dirpath, dirnames, filenames in os.walk(path):
            for entry in dirnames + filenames:
                file = Path(dirpath) / entry
                rel = file.relative_to(path).as_posix()
                if file.is_symlink():
                    raise UntrustedCheckpoint(f"{file} is a symbolic link; a checkpoint holds none")
                if entry in filenames and rel != CHECKSUMS and rel not in listed:
                    raise UntrustedCheckpoint(
                        f"{file} was not written with the checkpoint (it is not in {CHECKSUMS})"
                    )
                if entry.endswith(PICKLE_SUFFIXES):
                    raise UntrustedCheckpoint(
                        f"{file} holds pickled data, which torchrl-rave never writes and never "
                        "loads (unpickling runs code from the file)"
                    )
        try:
            records = Checkpoint.manifest(path)["components"].values()
            outside = [r["path"] for r in records if not _inside(str(r["path"]))]
        except Exception as err:  # noqa: BLE001 (any manifest damage is reported)
            raise DamagedCheckpoint(f"{path}/manifest.json is unreadable ({err})") from None
        if outside:
            raise UntrustedCheckpoint(f"{path}/manifest.json names {outside[0]!r}, outside {path}")

    # ------------------------------------------------------------------------ saving
    def preflight(self, expected_bytes: int | Callable[[int], int] = 0) -> None:
        """Before any training: the checkpoint directory can be created and written to and
        its filesystem has ``expected_bytes`` free (or ``expected_bytes(block)``, given the
        filesystem's block size); :class:`~torchrl_rave.recipe.checkpoint.CheckpointWriteError` otherwise."""
        probe = self.root / f".write-test-{uuid.uuid4().hex}"
        try:
            self.root.mkdir(parents=True, exist_ok=True)
            with probe.open("wb") as file:
                file.write(b"\0" * 4096)
                file.flush()
                os.fsync(file.fileno())
            probe.unlink()
        except OSError as err:
            with contextlib.suppress(OSError):
                probe.unlink()
            raise CheckpointWriteError(
                f"cannot write checkpoints to {self.root} ({err.strerror or err}); "
                "nothing was trained: make it writable or pick another run directory"
            ) from err
        if callable(expected_bytes):
            expected_bytes = expected_bytes(max(os.statvfs(self.root).f_frsize, 4096))
        self._check_space(int(expected_bytes), "a checkpoint of this run")

    def path(self, frames: int) -> Path:
        """Where checkpoint ``frames`` is (or would be written)."""
        return self.root / f"{PREFIX}{int(frames):012d}"

    def save(self, frames: int, **components) -> Path:
        """Writes checkpoint ``frames``; raises :class:`~torchrl_rave.recipe.checkpoint.CheckpointWriteError` (naming the
        directory and the cause) when it cannot, leaving the previous checkpoints intact."""
        destination = self.path(frames)
        stage = self.root / f".{destination.name}.writing-{uuid.uuid4().hex}"
        try:
            self.root.mkdir(parents=True, exist_ok=True)
            self._remove_leftovers()
            previous = self.checkpoints()
            if previous:  # same config, same sizes: the newest one says what this one needs
                self._check_space(_size(previous[-1]), f"checkpoint {destination.name}")
            checkpoint = _checkpoint(rng=GlobalRNGState(), **components)
            checkpoint.save(stage, metadata={"torchrl_rave_format": FORMAT_VERSION})
            self._write_checksums(stage)
            self._publish(stage, destination)
        except OSError as err:
            shutil.rmtree(stage, ignore_errors=True)
            raise self._write_error(destination, err) from err
        except BaseException:
            shutil.rmtree(stage, ignore_errors=True)
            raise
        self._prune()
        return destination

    def _write_checksums(self, stage: Path) -> None:
        files = {}
        for file in sorted(p for p in stage.rglob("*") if p.is_file()):
            _fsync(file)  # on disk before the name says it is there
            files[file.relative_to(stage).as_posix()] = [file.stat().st_size, _sha256(file)]
        with (stage / CHECKSUMS).open("w") as out:
            json.dump({"algorithm": "sha256", "files": files}, out, indent=1, sort_keys=True)
            out.flush()
            os.fsync(out.fileno())
        for directory in [stage, *(p for p in stage.rglob("*") if p.is_dir())]:
            _fsync(directory)

    def _publish(self, stage: Path, destination: Path) -> None:
        old = None
        if destination.exists():  # the same frame written again (a resumed run)
            old = self.root / f".{destination.name}.replaced-{uuid.uuid4().hex}"
            os.replace(destination, old)
        os.replace(stage, destination)
        _fsync(self.root)
        if old is not None:
            shutil.rmtree(old, ignore_errors=True)

    def _prune(self) -> None:
        for path in self.checkpoints()[:-KEEP_LAST]:
            doomed = self.root / f".{path.name}.delete-{uuid.uuid4().hex}"
            os.replace(path, doomed)
            shutil.rmtree(doomed, ignore_errors=True)

    def _remove_leftovers(self) -> None:
        """Half-written checkpoints of a killed process (hidden names) are deleted."""
        for path in self.root.iterdir():
            if path.name.startswith(".") and any(
                tag in path.name for tag in (".writing-", ".stage-", ".delete-", ".replaced-")
            ):
                shutil.rmtree(path, ignore_errors=True)

    def _check_space(self, needed: int, what: str) -> None:
        free = shutil.disk_usage(self.root).free
        needed = int(needed * 1.1) + (1 << 20)
        if free < needed:
            raise CheckpointWriteError(
                f"not enough disk space for {what} in {self.root}: about {needed / 1e6:.1f} "
                f"MB needed, {free / 1e6:.1f} MB free; free some space (the checkpoints "
                "already there are intact)"
            )

    def _write_error(self, destination: Path, err: OSError) -> CheckpointWriteError:
        if err.errno in (errno.ENOSPC, errno.EDQUOT):
            cause = "the disk is full"
        else:
            cause = err.strerror or str(err)
        previous = [p for p in self.checkpoints() if p != destination]
        kept = (
            f"the previous checkpoint {previous[-1]} is intact"
            if previous
            else ("there is no earlier checkpoint")
        )
        return CheckpointWriteError(f"could not write {destination}: {cause}; {kept}")

    # ----------------------------------------------------------------------- loading
    def load(self, *, path: Path | None = None, restore_rng: bool = True, **components) -> Path:
        """Restores ``components`` (and the RNG state) from the newest undamaged checkpoint,
        or ``path``, after checking their files against the checksums. Damaged newer
        checkpoints are moved to ``checkpoints/damaged/``, with a warning that says so."""
        if restore_rng:
            components["rng"] = GlobalRNGState()
        if path is None:
            path = self._newest_valid(list(components), set_aside=True)
            if path is None:
                raise FileNotFoundError(f"no checkpoint under {self.root} (resume needs one)")
        else:
            self.verify(path, list(components))
        _checkpoint(**components).load(path, components=list(components))
        return Path(path)

    def _newest_valid(self, components: list[str] | None, *, set_aside: bool) -> Path | None:
        damaged: list[tuple[Path, str]] = []
        for path in reversed(self.checkpoints()):
            try:
                self.verify(path, components)
            except DamagedCheckpoint as err:
                damaged.append((path, str(err)))
                continue
            if damaged:
                if set_aside:
                    self.set_aside([bad for bad, _ in damaged])
                moved = " (moved to checkpoints/damaged/)" if set_aside else ""
                warnings.warn(
                    f"skipped damaged checkpoint(s){moved}: "
                    f"{'; '.join(why for _, why in damaged)}; using the older {path}",
                    DamagedCheckpointWarning,
                    stacklevel=3,
                )
            return path
        if damaged:  # nothing to fall back to: everything stays where it is
            raise DamagedCheckpoint(
                f"every checkpoint under {self.root} is damaged: "
                f"{'; '.join(why for _, why in damaged)}"
            )
        return None

    def set_aside(self, paths: list[Path]) -> None:
        """Moves damaged checkpoints to ``checkpoints/damaged/``, so that neither a later
        load nor the pruning meets them."""
        if (self.root / "damaged").is_symlink():
            raise UnsafeRunDirectory(f"{self.root / 'damaged'} is a symbolic link")
        (self.root / "damaged").mkdir(exist_ok=True)
        for bad in paths:
            os.replace(bad, self.root / "damaged" / bad.name)

    def config(self) -> dict:
        """The config stored in the latest checkpoint, read without loading anything else."""
        return self.read("config")

    def read(self, name: str, path: Path | None = None):
        """One component of the newest undamaged (or the given) checkpoint as plain data:
        a state dict of tensors and Python values, or the JSON value."""
        if path is None:
            path = self._newest_valid([name], set_aside=False)
            if path is None:
                raise FileNotFoundError(f"no checkpoint found under {self.root}")
        else:
            self.verify(path, [name])
        record = Checkpoint.manifest(path)["components"].get(name)
        if record is None:
            raise KeyError(f"checkpoint {path} has no component {name!r}")
        target = {} if record["adapter"] == "torchrl.json" else _StateReader()
        try:
            Checkpoint(**{name: target}).load(path, components=[name])
        except Exception as err:  # noqa: BLE001 (torchrl's errors name no path)
            raise DamagedCheckpoint(
                f"{path}: its {name!r} component is unreadable ({type(err).__name__}: {err})"
            ) from None
        return target if isinstance(target, dict) else target.state

    def read_optional(self, name: str, path: Path):
        """:meth:`read` of a component that checkpoints written by an earlier torchrl-rave
        lack (e.g. ``episode``): ``None`` when checkpoint ``path`` has none."""
        if name not in Checkpoint.manifest(path)["components"]:
            return None
        return self.read(name, path)

    def _refuse_old_format(self) -> None:
        if (self.root / "latest").is_file():
            raise ValueError(
                f"{self.root} holds a checkpoint in the format of torchrl-rave before the "
                "torchrl.checkpoint redesign (a pickled state.pt, which this version never "
                "loads because unpickling runs code from the file). Start the run again, or "
                "resume it with the commit that wrote it."
            )


class _StateReader:
    """Receives a state dict from a checkpoint (the state-dict adapter needs an object)."""

    state = None

    def state_dict(self) -> dict:
        return {}

    def load_state_dict(self, state: dict) -> None:
        self.state = state


def check_new_run_dir(run_dir: str | Path, group: bool = False) -> None:
    """Refuses to start a run (``group``: a seed group) in a directory that already holds a
    resumable one: the new run would overwrite the old one's checkpoints and append to its
    metrics, and a resume between the two would mix them. A run stopped before its first
    checkpoint, or a group before every seed had one, has nothing to resume and may be
    started afresh."""
    root = Path(run_dir)
    seeds = _group_seeds(root)
    if seeds is not None:
        newest = [newest_frame(root / f"seed{s}") for s in seeds]
        if not group or None not in newest:
            raise FileExistsError(
                f"{root} holds a seed group already: pass resume={root} to continue it, "
                "or train into a new directory"
            )
    frame = newest_frame(root)
    if frame is not None:
        raise FileExistsError(
            f"{root} holds a run already (its newest checkpoint is at {frame} frames): pass "
            f"resume={root} to continue it, or train into a new directory"
        )


def newest_frame(run_dir: str | Path) -> int | None:
    """The frame of a run directory's newest checkpoint (damaged or not), or ``None``."""
    saved = RunCheckpoint(run_dir).checkpoints() if Path(run_dir).is_dir() else []
    return int(saved[-1].name.removeprefix(PREFIX)) if saved else None


def read_group_file(run_dir: str | Path) -> dict:
    """The config a seed group was last saved with (``<run_dir>/group.json``), as plain
    data; a file that is not a group's (malformed JSON, no ``config``, seeds that are not
    distinct non-negative integers) is named, with what it should hold."""
    path = Path(run_dir) / "group.json"
    if path.is_symlink():
        raise UnsafeRunDirectory(f"{path} is a symbolic link; a run directory holds none")
    try:
        cfg = json.loads(path.read_text())["config"]
        seeds = cfg["seeds"]
        ok = isinstance(seeds, list) and seeds and len(set(seeds)) == len(seeds)
        if not ok or not all(type(s) is int and s >= 0 for s in seeds):
            raise ValueError(f"seeds={seeds!r} is not a list of distinct integers >= 0")
    except (ValueError, KeyError, TypeError) as err:
        raise DamagedCheckpoint(
            f"{path} is not a seed group's file ({type(err).__name__}: {err}); it holds "
            '{"config": {..., "seeds": [...]}} as the group wrote it: restore it from a copy '
            "of the run directory"
        ) from None
    return cfg


def _group_seeds(run_dir: Path) -> list[int] | None:
    """The seeds of the seed group whose directory ``run_dir`` is, or ``None``."""
    if not (run_dir / "group.json").exists() and not (run_dir / "group.json").is_symlink():
        return None
    return read_group_file(run_dir)["seeds"]


def missing_checkpoint(run_dir: str | Path) -> FileNotFoundError:
    """The error for a directory with no checkpoint to read. A seed group's own directory
    (``seeds=``) has none: its runs are its ``seed<s>/`` directories, which it names. A
    path that does not exist, and a run's own ``checkpoints/`` folder given in place of the
    run, are named as such."""
    if not Path(run_dir).exists():
        return FileNotFoundError(f"{run_dir} does not exist: expected a run directory")
    if Path(run_dir).name == "checkpoints" and any(Path(run_dir).glob(f"{PREFIX}*")):
        return FileNotFoundError(
            f"{run_dir} is a run's checkpoints folder: pass the run directory that holds "
            f"it, {Path(run_dir).parent}"
        )
    seeds = _group_seeds(Path(run_dir))
    if seeds is not None:
        runs = [str(Path(run_dir) / f"seed{s}") for s in seeds]
        return FileNotFoundError(
            f"{run_dir} is a seed group's directory, which holds one run per seed; "
            f"use one of them: {runs}"
        )
    return FileNotFoundError(f"no checkpoint under {Path(run_dir) / 'checkpoints'}")


def saved_config(
    run_dir: str | Path, defaults: DictConfig | None = None, given: set[str] | None = None
) -> DictConfig:
    """The config a run (or a seed group, ``seeds=``) was saved with; keys added to
    ``defaults`` since take their defaults. It is read as data: a link out of the run
    directory, and an interpolation in the saved values (except at the keys in
    ``given``, which the caller sets itself), are refused
    (:func:`~torchrl_rave.recipe.trust.check_plain_data`)."""
    check_run_directory(run_dir)
    if _group_seeds(Path(run_dir)) is not None:
        data = read_group_file(run_dir)
    else:
        checkpoint = RunCheckpoint(run_dir)
        if not checkpoint.checkpoints():  # none at all (a damaged one is named by config())
            raise missing_checkpoint(run_dir)
        data = checkpoint.config()
    check_plain_data(data, given or set(), str(run_dir))
    saved = OmegaConf.create(data)
    return saved if defaults is None else OmegaConf.merge(defaults, saved)


def config_for_resume(
    run_dir: str | Path, overrides: list[str], defaults: DictConfig | None = None
) -> DictConfig:
    """The config a run was saved with, with command-line ``overrides`` applied on top. A
    ``preset=`` is refused: the run continues with the config it was saved with, and a
    preset would silently change nothing (name the keys to change instead). A saved value
    that would import a module, join a Ray cluster or open a file by name is refused unless
    ``overrides`` set its key (:mod:`torchrl_rave.recipe.trust`)."""
    given = {o.split("=", 1)[0].lstrip("+~") for o in overrides}
    saved = saved_config(run_dir, defaults, given)
    check_trusted(
        saved,
        given,
        f"resume={str(run_dir)!r}",
        "Pass the key on the command line with the value to use (the saved one, if you "
        "trust the run directory).",
    )
    if "preset" in given:
        raise ConfigError([
            f"resume={str(run_dir)!r}: preset= does not apply to a resumed run, which keeps "
            "the config it was saved with; set the keys to change one by one"
        ])  # fmt: skip
    keep = [o for o in overrides if o.split("=", 1)[0].lstrip("+~") != "resume"]
    cfg = OmegaConf.merge(saved, OmegaConf.from_dotlist(keep))
    cfg.resume = str(run_dir)
    return cfg
