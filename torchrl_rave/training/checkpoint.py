"""Run checkpoints through ``torchrl.checkpoint``: no pickle on load, the last two kept."""

from __future__ import annotations

from pathlib import Path

from omegaconf import DictConfig, OmegaConf
from torchrl.checkpoint import Checkpoint, CheckpointAdapter, CheckpointRotation, GlobalRNGState
from torchrl.data import ReplayBuffer

__all__ = ["FORMAT_VERSION", "RunCheckpoint", "config_for_resume", "saved_config"]

# written into every manifest's metadata; a run directory without it predates this format
FORMAT_VERSION = 2


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


class RunCheckpoint:
    """The checkpoints of one run: ``<run_dir>/checkpoints/checkpoint-<frames>/``.

    Each is a ``torchrl.checkpoint.Checkpoint`` directory, written in a staging directory
    and published atomically, so a kill at any moment leaves the previous one whole. The
    two newest are kept. Tensors are stored as TensorDict memory maps and everything else
    as JSON: loading one runs no code from it (no pickle).

    The components are the ones passed to :meth:`save` / :meth:`load`: live objects with
    ``state_dict``/``load_state_dict`` (modules, optimisers, the world-model trainer),
    ``dump``/``load`` (the replay buffer) or plain JSON dicts (config, counters), updated
    in place on load; the process's RNG state is always included.
    """

    def __init__(self, run_dir: str | Path) -> None:
        self.root = Path(run_dir) / "checkpoints"
        self.rotation = CheckpointRotation(self.root, keep_last=2)

    def latest(self) -> Path | None:
        self._refuse_old_format()
        return self.rotation.latest()

    def save(self, frames: int, **components) -> Path:
        checkpoint = _checkpoint(rng=GlobalRNGState(), **components)
        return self.rotation.save(
            checkpoint, step=int(frames), metadata={"torchrl_rave_format": FORMAT_VERSION}
        )

    def load(self, *, path: Path | None = None, restore_rng: bool = True, **components) -> Path:
        """Restores ``components`` (and the RNG state) from the latest checkpoint, or ``path``."""
        path = path or self.latest()
        if path is None:
            raise FileNotFoundError(f"no checkpoint under {self.root} (resume needs one)")
        if restore_rng:
            components["rng"] = GlobalRNGState()
        _checkpoint(**components).load(path, components=list(components))
        return path

    def config(self) -> dict:
        """The config stored in the latest checkpoint, read without loading anything else."""
        return self.read("config")

    def read(self, name: str, path: Path | None = None):
        """One component of the latest (or the given) checkpoint as plain data: a state
        dict of tensors and Python values, or the JSON value."""
        path = path or self.latest()
        if path is None:
            raise FileNotFoundError(f"no checkpoint found under {self.root}")
        record = Checkpoint.manifest(path)["components"].get(name)
        if record is None:
            raise KeyError(f"checkpoint {path} has no component {name!r}")
        target = {} if record["adapter"] == "torchrl.json" else _StateReader()
        Checkpoint(**{name: target}).load(path, components=[name])
        return target if isinstance(target, dict) else target.state

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


def saved_config(run_dir: str | Path, defaults: DictConfig | None = None) -> DictConfig:
    """The config a run was saved with; keys added to ``defaults`` since take their defaults."""
    saved = OmegaConf.create(RunCheckpoint(run_dir).config())
    return saved if defaults is None else OmegaConf.merge(defaults, saved)


def config_for_resume(
    run_dir: str | Path, overrides: list[str], defaults: DictConfig | None = None
) -> DictConfig:
    """The config a run was saved with, with command-line ``overrides`` applied on top."""
    saved = saved_config(run_dir, defaults)
    keep = [o for o in overrides if o.split("=", 1)[0].lstrip("+~") not in ("resume", "preset")]
    cfg = OmegaConf.merge(saved, OmegaConf.from_dotlist(keep))
    cfg.resume = str(run_dir)
    return cfg
