"""Faults lose nothing and hide nothing (issue 15): checkpoints are checksummed and the
older one is used when the newest is damaged; an unwritable directory, a full disk, a hung
worker and NaN in the evaluation env are each named before any work is lost.

The faults are real where they can be: truncated and corrupted files, a file where the
checkpoint directory should be, a 1 MiB tmpfs (where this process may mount one), a worker
that sleeps forever."""

from __future__ import annotations

import errno
import json
import os
import shutil
import signal
import subprocess
import sys
import threading
import time
import uuid
from pathlib import Path

import pytest
import rave_mujoco
import torch
from tensordict import TensorDict
from test_recipe import TINY, make_cfg
from torch import nn
from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer

from torchrl_rave.recipe import loop
from torchrl_rave.recipe.checkpoint import (
    CheckpointWriteError,
    DamagedCheckpoint,
    DamagedCheckpointWarning,
    ReplayBufferAdapter,
    RunCheckpoint,
    RunInUse,
    exclusive_run,
)
from torchrl_rave.recipe.collect import CollectorTimeout, NonFiniteEnvOutput, deadline
from torchrl_rave.recipe.runs import Cell, GridStopped, launch_grid

FRAMES = 500  # frames in the small test buffer


def replay_buffer(frames: int = FRAMES, seed: int = 0) -> TensorDictReplayBuffer:
    rb = TensorDictReplayBuffer(storage=LazyTensorStorage(1000), batch_size=8)
    if frames == 0:  # an empty buffer to load into
        return rb
    gen = torch.Generator().manual_seed(seed)
    rb.extend(
        TensorDict(
            observation=torch.randn(frames, 11, generator=gen),
            reward=torch.randn(frames, 1, generator=gen),
            batch_size=[frames],
        )
    )
    return rb


def save_two(run_dir: Path) -> tuple[RunCheckpoint, nn.Module]:
    """Checkpoints 100 (buffer of 500 frames, module weights 1) and 200 (600 frames, 2)."""
    checkpoint = RunCheckpoint(run_dir)
    net = nn.Linear(3, 2)
    for frames, fill, n in ((100, 1.0, FRAMES), (200, 2.0, FRAMES + 100)):
        nn.init.constant_(net.weight, fill)
        checkpoint.save(frames, net=net, replay_buffer=replay_buffer(n), counters={"f": frames})
    return checkpoint, net


def buffer_file(checkpoint_dir: Path) -> Path:
    """The replay buffer's ``observation`` file (not ``("next", "observation")``)."""
    return min(checkpoint_dir.rglob("observation.memmap"), key=lambda p: len(p.parts))


class TestChecksums:
    def test_checksums_cover_every_file_and_two_checkpoints_are_kept(self, tmp_path):
        checkpoint, net = save_two(tmp_path)
        checkpoint.save(300, net=net, replay_buffer=replay_buffer(), counters={"f": 300})
        names = sorted(p.name for p in checkpoint.root.iterdir())
        assert names == ["checkpoint-000000000200", "checkpoint-000000000300"]
        newest = checkpoint.root / names[-1]
        listed = json.loads((newest / "checksums.json").read_text())["files"]
        on_disk = {
            p.relative_to(newest).as_posix()
            for p in newest.rglob("*")
            if p.is_file() and p.name != "checksums.json"
        }
        assert set(listed) == on_disk and "manifest.json" in listed
        assert any(name.endswith("observation.memmap") for name in listed)

    @pytest.mark.parametrize("damage", ["truncate", "flip_a_byte", "delete", "manifest"])
    def test_a_damaged_newest_checkpoint_falls_back_to_the_older_and_says_so(
        self, damage, tmp_path
    ):
        checkpoint, _ = save_two(tmp_path)
        newest = checkpoint.root / "checkpoint-000000000200"
        target = newest / "manifest.json" if damage == "manifest" else buffer_file(newest)
        data = target.read_bytes()
        if damage == "truncate":  # what a full disk or a killed copy leaves
            target.write_bytes(data[: len(data) // 3])
        elif damage in ("flip_a_byte", "manifest"):  # same size, different content
            target.write_bytes(data[:40] + bytes([data[40] ^ 0xFF]) + data[41:])
        else:
            target.unlink()
        rb, net = replay_buffer(0), nn.Linear(3, 2)
        counters = {}
        with pytest.warns(DamagedCheckpointWarning, match=f"{target.name}.*using the older"):
            used = checkpoint.load(net=net, replay_buffer=rb, counters=counters)
        assert used.name == "checkpoint-000000000100"
        assert counters == {"f": 100} and len(rb) == FRAMES
        assert torch.equal(rb[:FRAMES]["observation"], replay_buffer()[:FRAMES]["observation"])
        assert torch.all(net.weight == 1.0)
        # the damaged one is set aside, not deleted and not loaded again
        assert (checkpoint.root / "damaged" / newest.name).is_dir()
        assert not newest.exists()

    def test_a_buffer_saved_again_right_after_loading_round_trips_without_a_warning(
        self, tmp_path, recwarn
    ):
        """A resumed run can checkpoint before it writes to its buffer (a stop during its
        owed updates). TorchRL then warns that the buffer "may not be saved properly"
        (its storage's write cursor is unset after a load); with no save hooks nothing
        reads that cursor, and the buffer comes back whole."""
        first = RunCheckpoint(tmp_path / "first")
        first.save(100, replay_buffer=replay_buffer())
        loaded = replay_buffer(0)
        first.load(replay_buffer=loaded)
        second = RunCheckpoint(tmp_path / "second")
        second.save(100, replay_buffer=loaded)
        assert not [w for w in recwarn if issubclass(w.category, UserWarning)], [
            str(w.message) for w in recwarn
        ]
        again = replay_buffer(0)
        second.load(replay_buffer=again)
        assert len(again) == FRAMES
        assert torch.equal(again[:FRAMES]["observation"], replay_buffer()[:FRAMES]["observation"])
        # the writer goes on where the saved buffer's did
        more = replay_buffer(10, seed=1)[:10]
        again.extend(more)
        assert len(again) == FRAMES + 10
        assert torch.equal(again[FRAMES : FRAMES + 10]["observation"], more["observation"])

    def test_a_truncated_buffer_is_never_loaded_silently(self, tmp_path):
        """Defect 3: the buffer came back as zeros and was trained on."""
        checkpoint = RunCheckpoint(tmp_path)
        checkpoint.save(100, replay_buffer=replay_buffer())
        path = buffer_file(checkpoint.root / "checkpoint-000000000100")
        path.write_bytes(path.read_bytes()[: path.stat().st_size // 3])
        with pytest.raises(DamagedCheckpoint, match=rf"every checkpoint.*{path}.* bytes, \d+ were"):
            checkpoint.load(replay_buffer=replay_buffer(0))
        # naming one checkpoint explicitly is checked the same way
        with pytest.raises(DamagedCheckpoint, match=str(path)):
            checkpoint.load(
                path=checkpoint.root / "checkpoint-000000000100", replay_buffer=replay_buffer(0)
            )

    def test_reading_for_analysis_falls_back_without_moving_anything(self, tmp_path):
        checkpoint, _ = save_two(tmp_path)
        newest = checkpoint.root / "checkpoint-000000000200"
        (newest / "checksums.json").unlink()
        with pytest.warns(DamagedCheckpointWarning, match="no checksums.json"):
            assert checkpoint.read("counters") == {"f": 100}
        assert newest.is_dir()  # read() only reads

    def test_a_killed_save_leaves_nothing_that_is_loaded_and_is_cleaned_up(self, tmp_path):
        checkpoint, net = save_two(tmp_path)
        # what a kill in the middle of save() leaves: a hidden, half-written directory
        half = checkpoint.root / f".checkpoint-000000000300.writing-{uuid.uuid4().hex}"
        shutil.copytree(checkpoint.root / "checkpoint-000000000200", half)
        (half / "checksums.json").unlink()
        assert checkpoint.latest().name == "checkpoint-000000000200"
        checkpoint.save(300, net=net, counters={"f": 300})
        assert not half.exists()


class TestWriteFailures:
    def test_an_unwritable_checkpoint_directory_fails_before_training(self, tmp_path):
        """Defect 5: the first 1,500 frames were lost. A file where the directory should
        be is unwritable for root too (permission bits are not)."""
        (tmp_path / "checkpoints").write_text("not a directory")
        cfg = make_cfg(*TINY, "algorithm=ddpg", "logger.backend=csv")
        t0 = time.perf_counter()
        with pytest.raises(
            CheckpointWriteError, match=r"cannot write checkpoints to .*checkpoints"
        ):
            rave_mujoco.train(cfg, str(tmp_path))
        assert time.perf_counter() - t0 < 30
        assert not (tmp_path / "ddpg").exists()  # no metric was logged: nothing ran

    def test_a_write_that_fails_keeps_the_previous_checkpoint_and_names_the_cause(
        self, monkeypatch, tmp_path
    ):
        """Defect 6 (simulated): the disk fills up while the buffer is written."""
        checkpoint, net = save_two(tmp_path)

        def full_disk(self, component, path, **kwargs):
            path.mkdir(parents=True)
            (path / "partial").write_bytes(b"\0" * 100)
            raise OSError(errno.ENOSPC, "No space left on device", str(path / "partial"))

        monkeypatch.setattr(ReplayBufferAdapter, "save", full_disk)
        with pytest.raises(
            CheckpointWriteError,
            match=r"could not write .*checkpoint-000000000300: the disk is full; the previous "
            r"checkpoint .*checkpoint-000000000200 is intact",
        ):
            checkpoint.save(300, net=net, replay_buffer=replay_buffer())
        # nothing half-written is left, and the two earlier checkpoints are whole
        assert sorted(p.name for p in checkpoint.root.iterdir()) == [
            "checkpoint-000000000100",
            "checkpoint-000000000200",
        ]
        checkpoint.verify(checkpoint.root / "checkpoint-000000000200")

    def test_too_little_space_is_refused_before_writing(self, monkeypatch, tmp_path):
        checkpoint, net = save_two(tmp_path)
        size = sum(f.stat().st_size for f in checkpoint.latest().rglob("*") if f.is_file())
        usage = shutil.disk_usage(tmp_path)
        monkeypatch.setattr(shutil, "disk_usage", lambda path: usage._replace(free=size // 2))
        with pytest.raises(CheckpointWriteError, match=r"not enough disk space .* MB free"):
            checkpoint.save(300, net=net, replay_buffer=replay_buffer())
        with pytest.raises(CheckpointWriteError, match=r"not enough disk space"):
            checkpoint.preflight(size)


@pytest.fixture
def small_filesystem(tmp_path):
    """A real 1 MiB filesystem (tmpfs), where this process may mount one (root with
    CAP_SYS_ADMIN, as on the project's machines)."""
    mount = tmp_path / "small"
    mount.mkdir()
    done = subprocess.run(
        ["mount", "-t", "tmpfs", "-o", "size=1m", "tmpfs", str(mount)], capture_output=True
    )
    if done.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here: {done.stderr.decode().strip()}")
    yield mount
    subprocess.run(["umount", "-l", str(mount)], check=False)


def test_a_small_filesystem_is_refused_before_training(small_filesystem):
    """Defect 6 for real: memory-mapped writes on a full tmpfs kill the process with
    SIGBUS, so the space is checked before any work."""
    cfg = make_cfg(*TINY, "algorithm=ddpg", "replay_buffer.size=100000")
    with pytest.raises(CheckpointWriteError, match=r"not enough disk space for a checkpoint"):
        rave_mujoco.train(cfg, str(small_filesystem / "run"))


@pytest.mark.parametrize("algorithm", ["rave", "sac", "ppo"])
def test_the_space_estimate_bounds_a_real_checkpoint(tmp_path, algorithm):
    """Defect 4 of the second round: the estimate counted bytes, not the blocks a
    checkpoint's 250-odd small files take, so a filesystem with room for the estimate but
    not for the checkpoint passed the check and the first save died of SIGBUS."""
    from torchrl_rave.recipe.agent import make_agent, make_env
    from torchrl_rave.recipe.checkpoint import _size
    from torchrl_rave.recipe.config import replay_buffer_size, resolve_config

    cfg = make_cfg(*TINY, f"algorithm={algorithm}", "env.name=Hopper-v5")
    rave_mujoco.train(cfg, str(tmp_path))
    real = _size(RunCheckpoint(tmp_path).latest())
    cfg = resolve_config(cfg)
    env = make_env(cfg, torch.device("cpu"))
    agent = make_agent(cfg, env)
    estimate = agent.checkpoint_bytes(replay_buffer_size(cfg), env.fake_tensordict(), 4096)
    assert real <= estimate <= 1.6 * real, (real, estimate)


def test_a_full_disk_between_checkpoints_is_named(small_filesystem):
    """The first checkpoint fits; filling the disk before the second is refused by name
    and the first stays loadable."""
    checkpoint = RunCheckpoint(small_filesystem / "run")
    checkpoint.save(100, replay_buffer=replay_buffer(200))
    filler = small_filesystem / "filler"
    with open(filler, "wb", buffering=0) as out:
        try:
            while True:
                out.write(b"\0" * 4096)
        except OSError as err:
            assert err.errno == errno.ENOSPC
    with pytest.raises(CheckpointWriteError, match="not enough disk space"):
        checkpoint.save(200, replay_buffer=replay_buffer(200))
    filler.unlink()
    rb = replay_buffer(0)
    checkpoint.load(replay_buffer=rb, restore_rng=False)
    assert len(rb) == 200


class TestRecipe:
    def test_resume_falls_back_past_a_truncated_buffer(self, tmp_path, recwarn):
        """Defect 3 end to end: the buffer of the newest checkpoint is cut to a third; the
        resumed run starts from the older checkpoint, says so, and finishes."""
        first = make_cfg(*TINY, "algorithm=ddpg", "collector.total_frames=300",
                         "checkpoint.interval=100")  # fmt: skip
        rave_mujoco.train(first, str(tmp_path))
        checkpoint = RunCheckpoint(tmp_path)
        assert [p.name[-3:] for p in checkpoint.checkpoints()] == ["200", "300"]
        path = buffer_file(checkpoint.checkpoints()[-1])
        path.write_bytes(path.read_bytes()[: path.stat().st_size // 3])
        more = make_cfg(*TINY, "algorithm=ddpg", f"resume={tmp_path}")
        result = rave_mujoco.train(more, str(tmp_path))
        warned = [str(w.message) for w in recwarn if w.category is DamagedCheckpointWarning]
        assert warned and "checkpoint-000000000200" in warned[0]
        assert result["frames"] == 400
        assert checkpoint.read("counters")["frames"] == 400
        assert (checkpoint.root / "damaged" / "checkpoint-000000000300").is_dir()

    def test_nan_in_the_evaluation_env_stops_with_a_checkpoint(self, monkeypatch, tmp_path):
        """Defect 8: eval/return was logged as nan, printed as nan ± nan, and the run
        exited 0. The recipe builds the training env first and the evaluation env second;
        the second gets NaN observations."""
        from torchrl.envs import TransformedEnv
        from torchrl.envs.transforms import Transform

        class NaNObservation(Transform):
            def _call(self, next_tensordict):
                next_tensordict["observation"] = next_tensordict["observation"] * float("nan")
                return next_tensordict

        made = []

        def make_env(cfg, device, **kwargs):
            env = original(cfg, device, **kwargs)
            made.append(env)
            return TransformedEnv(env, NaNObservation()) if len(made) == 2 else env

        original = loop.make_env
        monkeypatch.setattr(loop, "make_env", make_env)
        cfg = make_cfg(*TINY, "algorithm=ddpg")
        with pytest.raises(
            NonFiniteEnvOutput,
            match=r"evaluation env produced NaN/inf in .*observation.* at frame 200; checkpoint",
        ):
            rave_mujoco.train(cfg, str(tmp_path))
        assert RunCheckpoint(tmp_path).read("counters")["frames"] == 200


@pytest.mark.parametrize(
    "backend",
    [["collector.backend=direct"], ["collector.backend=process", "collector.num_workers=1"]],
    ids=["direct", "process"],
)
def test_a_hung_worker_is_stopped_within_the_timeout(backend, tmp_path):
    """Defect 7: a worker that sleeps forever (step 150) hung the learner until killed.
    Now the batch it never delivers times out, the state after the last whole batch is
    checkpointed, and the run fails like a crashed worker."""
    cfg = make_cfg(*TINY, *backend, "algorithm=ddpg", "collector.timeout_s=8",
                   "env.name=failing_env:HangingPendulum-v0")  # fmt: skip
    t0 = time.perf_counter()
    with pytest.raises(CollectorTimeout, match=r"within collector.timeout_s=8 s after frame 100"):
        rave_mujoco.train(cfg, str(tmp_path))
    assert time.perf_counter() - t0 < 90
    assert RunCheckpoint(tmp_path).read("counters")["frames"] == 100


def wait(seconds: float) -> None:
    """Waits in short sleeps, as a collector polls its workers. (One long ``time.sleep``
    is not woken when the alarm lands on another of pytest's threads.)"""
    end = time.perf_counter() + seconds
    while time.perf_counter() < end:
        time.sleep(0.05)


class TestDeadline:
    """The per-batch deadline behind ``collector.timeout_s``."""

    def test_a_block_past_its_deadline_raises(self):
        t0 = time.perf_counter()
        with pytest.raises(CollectorTimeout, match="stuck"), deadline(0.5, "stuck"):
            wait(5)
        # the alarm, then the grace for a SIGCONT that does not come
        assert 0.5 + 0.9 < time.perf_counter() - t0 < 4

    def test_a_stopped_process_is_not_hung(self):
        """A run paused with SIGSTOP (as when its cores are wanted elsewhere) for longer
        than the deadline, then continued, finishes its batch: the wait starts afresh."""
        pid = os.getpid()
        pauser = subprocess.Popen(
            ["sh", "-c", f"sleep 0.3; kill -STOP {pid}; sleep 2.5; kill -CONT {pid}"]
        )
        t0 = time.perf_counter()
        try:
            with deadline(1.0, "stuck"):
                wait(3.3)  # stopped from 0.3 s to 2.8 s; 0.5 s of waiting after
        finally:
            pauser.wait()
        assert time.perf_counter() - t0 >= 3.3
        # and a block that then waits past the renewed deadline still raises
        pauser = subprocess.Popen(
            ["sh", "-c", f"sleep 0.3; kill -STOP {pid}; sleep 1.5; kill -CONT {pid}"]
        )
        try:
            with pytest.raises(CollectorTimeout), deadline(1.0, "stuck"):
                wait(6)
        finally:
            pauser.wait()


class TestStoppingRuns:
    """A run directory has one trainer at a time, and a grid stops the way one run does."""

    def test_a_second_trainer_is_refused_and_a_killed_holder_leaves_no_lock(self, tmp_path):
        holder = subprocess.Popen(
            [sys.executable, "-c", HOLD_LOCK, str(tmp_path)], stdout=subprocess.PIPE, text=True
        )
        try:
            assert holder.stdout.readline().strip() == "held"
            with pytest.raises(RunInUse, match=rf"{tmp_path} is in use: process {holder.pid} "):
                rave_mujoco.train(make_cfg(*TINY), str(tmp_path))
            assert not (tmp_path / "checkpoints").exists()  # refused before any work
            cfg = make_cfg(*TINY, f"resume={tmp_path}")
            with pytest.raises(RunInUse, match=str(holder.pid)):
                rave_mujoco.train(cfg, str(tmp_path / "unused"))
        finally:
            holder.kill()
            holder.wait()
        # the lock died with its holder; and one process does not hold it twice
        with (
            exclusive_run(tmp_path),
            pytest.raises(RunInUse, match=str(os.getpid())),
            exclusive_run(tmp_path),
        ):
            pass
        with exclusive_run(tmp_path):  # released at the end of the block
            pass

    def test_a_stopped_grid_passes_the_signal_on_once_and_starts_no_more(self, tmp_path):
        if threading.current_thread() is not threading.main_thread():
            pytest.skip("signal handlers can only be set from the main thread")
        cells = [Cell(tmp_path / f"cell{i}", frames=100) for i in range(3)]

        def stop_once_two_run():
            end = time.perf_counter() + 120
            while time.perf_counter() < end:
                if all((c.run_dir / "started").exists() for c in cells[:2]):
                    os.kill(os.getpid(), signal.SIGTERM)
                    return
                time.sleep(0.05)

        before = signal.getsignal(signal.SIGTERM)
        threading.Thread(target=stop_once_two_run, daemon=True).start()
        ended = []
        with pytest.raises(GridStopped) as stop:
            launch_grid(GRID_CELL, cells, jobs=2, on_done=lambda c, code: ended.append(c))
        for c in cells[:2]:  # each got the signal once, and ran to its own end
            assert (c.run_dir / "signals").read_text() == str(int(signal.SIGTERM))
            pid, session = map(int, (c.run_dir / "started").read_text().split())
            assert session == pid != os.getsid(0)  # out of reach of a terminal's Ctrl-C
            assert str(c.run_dir) in str(stop.value)
        assert not cells[2].run_dir.exists()
        assert "stopped by SIGTERM: 2 run(s) checkpointed" in str(stop.value)
        assert "1 run(s) had not started" in str(stop.value)
        assert ended == []  # stopped, not done
        assert signal.getsignal(signal.SIGTERM) is before

    def test_a_grid_writes_down_each_start_and_the_checkpoint_it_resumes_from(self, tmp_path):
        script = tmp_path / "argv.py"  # a stand-in run: it writes down its arguments
        script.write_text(
            "import sys, pathlib\n"
            "d = next(a.split('=', 1)[1] for a in sys.argv if a.startswith('hydra.run.dir='))\n"
            "pathlib.Path(d, 'argv').write_text(' '.join(sys.argv[1:]))\n"
        )
        fresh, resumed = Cell(tmp_path / "fresh", 100), Cell(tmp_path / "resumed", 100)
        for name in ("checkpoint-250", "checkpoint-500", ".checkpoint-750"):  # hidden: half-written
            (resumed.run_dir / "checkpoints" / name).mkdir(parents=True)
        codes = launch_grid(script, [fresh, resumed], record={"commit": "abc"})
        assert codes == {fresh: 0, resumed: 0}
        assert [s["from_frame"] for s in resumed.starts()] == [500]
        assert f"resume={resumed.run_dir}" in (resumed.run_dir / "argv").read_text()
        assert "resume=" not in (fresh.run_dir / "argv").read_text()
        (fresh.run_dir / "checkpoints" / "checkpoint-50").mkdir(parents=True)
        launch_grid(script, [fresh], record={"commit": "def"})  # a later session's commit
        starts = fresh.starts()
        assert [(s["commit"], s["from_frame"]) for s in starts] == [("abc", 0), ("def", 50)]
        assert all(len(s["at"]) >= 19 for s in starts)
        assert Cell(tmp_path / "never", 100).starts() == []


GRID_CELL = Path(__file__).with_name("grid_cell.py")
HOLD_LOCK = """import sys, time
from torchrl_rave.recipe.checkpoint import exclusive_run
with exclusive_run(sys.argv[1]):
    print("held", flush=True)
    time.sleep(600)
"""
