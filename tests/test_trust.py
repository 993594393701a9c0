"""The trust boundary of a run directory, probed as an attacker would: a crafted run
directory (planted pickles, extra files, links, a saved config that names a module, an
address or a file) never runs code, imports a module, connects anywhere, or makes a write
or a read land outside it."""

from __future__ import annotations

import json
import os
import shutil
import sqlite3
import time
from pathlib import Path

import pytest
import rave_mujoco
import torch
from tensordict import NonTensorData, TensorDict
from test_recipe import TINY, make_cfg

from torchrl_rave.recipe import load_agent, load_policy
from torchrl_rave.recipe.checkpoint import (
    CHECKSUMS,
    DamagedCheckpoint,
    DamagedCheckpointWarning,
    RunCheckpoint,
    UnsafeRunDirectory,
    config_for_resume,
)
from torchrl_rave.recipe.config import ConfigError, check_config
from torchrl_rave.recipe.runs import read_scalar, relogged, train_seconds
from torchrl_rave.recipe.schema import defaults
from torchrl_rave.recipe.trust import UntrustedRunConfig, reach_ray_address

RUN = [*TINY, "algorithm=ddpg", "env.name=Hopper-v5", "collector.total_frames=300",
       "checkpoint.interval=100"]  # fmt: skip


class Payload:
    """Unpickling it creates the directory ``marker``: proof that code ran."""

    def __init__(self, marker: Path) -> None:
        self.marker = str(marker)

    def __reduce__(self):
        return (os.mkdir, (self.marker,))


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    run = tmp_path_factory.mktemp("trained")
    rave_mujoco.train(make_cfg(*RUN), str(run))
    return run


@pytest.fixture
def run(trained, tmp_path):
    """A fresh copy of the trained run directory, with its two checkpoints (200 and 300)."""
    copy = tmp_path / "run"
    shutil.copytree(trained, copy)
    return copy


def rechecksum(checkpoint: Path) -> None:
    """What anyone can do: rewrite checksums.json to match whatever the directory holds."""
    (checkpoint / CHECKSUMS).unlink()
    RunCheckpoint(checkpoint.parent.parent)._write_checksums(checkpoint)


def component(checkpoint: Path, name: str) -> Path:
    (found,) = [p for p in (checkpoint / "components").iterdir() if p.name.endswith(f"-{name}")]
    return found


def plant_pickle(tensordict_dir: Path, marker: Path) -> None:
    """Adds a non-tensor entry whose pickle runs ``Payload`` to a TensorDict memory-map
    directory, the way tensordict itself stores non-tensor data."""
    TensorDict(evil=NonTensorData(Payload(marker))).memmap(tensordict_dir.parent / "_evil")
    shutil.move(tensordict_dir.parent / "_evil" / "evil", tensordict_dir / "evil")
    shutil.rmtree(tensordict_dir.parent / "_evil")
    meta = json.loads((tensordict_dir / "meta.json").read_text())
    meta["evil"] = {"type": "NonTensorData"}
    (tensordict_dir / "meta.json").write_text(json.dumps(meta))


def latest(run: Path) -> Path:
    return RunCheckpoint(run).checkpoints()[-1]


def edit_config(run: Path, **changes) -> None:
    """Changes the saved config of every checkpoint, checksums rewritten."""
    for checkpoint in RunCheckpoint(run).checkpoints():
        path = component(checkpoint, "config") / "value.json"
        cfg = json.loads(path.read_text())
        for dotted, value in changes.items():
            node = cfg
            *parents, leaf = dotted.split(".")
            for part in parents:
                if not isinstance(node.get(part), dict):
                    node[part] = {}
                node = node[part]
            node[leaf] = value
        path.write_text(json.dumps(cfg))
        rechecksum(checkpoint)


class TestPickles:
    def test_a_planted_pickle_in_the_policy_is_never_unpickled(self, run, tmp_path):
        marker = tmp_path / "ran"
        plant_pickle(component(latest(run), "policy") / "state", marker)
        rechecksum(latest(run))
        with pytest.warns(DamagedCheckpointWarning, match="pickled data"):
            policy = load_policy(run)
        assert not marker.exists()
        assert policy(TensorDict(observation=torch.zeros(11)))["action"].shape == (3,)

    def test_a_planted_pickle_in_the_replay_buffer_is_never_unpickled(self, run, tmp_path):
        marker = tmp_path / "ran"
        plant_pickle(component(latest(run), "replay_buffer") / "storage", marker)
        rechecksum(latest(run))
        more = make_cfg(*RUN, "collector.total_frames=400", f"resume={run}")
        with pytest.warns(DamagedCheckpointWarning, match="pickled data"):
            result = rave_mujoco.train(more, str(run))
        assert not marker.exists()
        assert result["frames"] == 400  # resumed from the older checkpoint

    def test_every_checkpoint_tampered_is_refused_outright(self, run, tmp_path):
        marker = tmp_path / "ran"
        for checkpoint in RunCheckpoint(run).checkpoints():
            plant_pickle(component(checkpoint, "policy") / "state", marker)
            rechecksum(checkpoint)
        with pytest.raises(DamagedCheckpoint, match="every checkpoint .* pickled data"):
            load_policy(run)
        assert not marker.exists()

    @pytest.mark.parametrize("listed", [False, True])
    def test_a_planted_state_pt_is_refused(self, run, listed):
        """An extra ``state.pt`` with other weights, listed in rewritten checksums or not."""
        target = component(latest(run), "policy") / "state.pt"
        torch.save({"weight": torch.ones(3)}, target)
        if listed:
            rechecksum(latest(run))
        with pytest.warns(DamagedCheckpointWarning, match="state.pt"):
            load_policy(run)

    def test_a_checksum_entry_leading_outside_is_refused(self, run, tmp_path):
        outside = tmp_path / "secret"
        outside.write_text("x")
        path = latest(run) / CHECKSUMS
        listed = json.loads(path.read_text())
        listed["files"]["../../../secret"] = [1, "0" * 64]
        path.write_text(json.dumps(listed))
        with pytest.warns(DamagedCheckpointWarning, match="outside"):
            load_policy(run)


class TestLinks:
    def test_a_linked_lock_file_is_refused_and_its_target_kept(self, run, tmp_path):
        target = tmp_path / "precious"
        target.write_text("keep me")
        (run / ".run.lock").unlink()
        (run / ".run.lock").symlink_to(target)
        with pytest.raises(UnsafeRunDirectory, match="run.lock is a symbolic link"):
            rave_mujoco.train(make_cfg(*RUN, f"resume={run}"), str(run))
        assert target.read_text() == "keep me"

    def test_a_linked_metric_file_is_refused_and_its_target_kept(self, run, tmp_path):
        target = tmp_path / "precious.csv"
        target.write_text("keep me\n")
        csv = run / "ddpg" / "scalars" / "eval" / "return.csv"
        csv.unlink()
        csv.symlink_to(target)
        more = make_cfg(*RUN, "collector.total_frames=400", f"resume={run}")
        with pytest.raises(
            UnsafeRunDirectory, match="return.csv is a symbolic link to .*outside the run"
        ):
            rave_mujoco.train(more, str(run))
        assert target.read_text() == "keep me\n"

    def test_a_linked_component_directory_is_refused(self, run, tmp_path):
        """A link out of the run directory is refused before any checkpoint is chosen;
        one that stays inside it makes only its checkpoint damaged (a checkpoint holds no
        links), and the older one is used."""
        policy = component(latest(run), "policy")
        shutil.move(policy, tmp_path / "elsewhere")
        policy.symlink_to(tmp_path / "elsewhere")
        with pytest.raises(UnsafeRunDirectory, match="policy is a symbolic link to .*outside"):
            load_policy(run)
        shutil.move(tmp_path / "elsewhere", run / "elsewhere")
        policy.unlink()
        policy.symlink_to(run / "elsewhere")
        with pytest.warns(DamagedCheckpointWarning, match="symbolic link"):
            load_policy(run)

    def test_a_linked_damaged_directory_receives_nothing(self, run, tmp_path):
        outside = tmp_path / "outside"
        outside.mkdir()
        (run / "checkpoints" / "damaged").symlink_to(outside)
        (component(latest(run), "counters") / "value.json").write_text("{}")
        more = make_cfg(*RUN, "collector.total_frames=400", f"resume={run}")
        with pytest.raises(UnsafeRunDirectory, match="damaged is a symbolic link"):
            rave_mujoco.train(more, str(run))
        assert list(outside.iterdir()) == []

    def test_a_saved_experiment_name_does_not_lead_the_metrics_out(self, run, tmp_path):
        for checkpoint in RunCheckpoint(run).checkpoints():
            path = component(checkpoint, "logger") / "value.json"
            state = json.loads(path.read_text())
            state["exp_name"] = "../escaped"
            path.write_text(json.dumps(state))
            rechecksum(checkpoint)
        more = make_cfg(*RUN, "collector.total_frames=400", f"resume={run}")
        rave_mujoco.train(more, str(run))
        assert not (tmp_path / "escaped").exists()
        rows = (run / "ddpg" / "scalars" / "eval" / "return.csv").read_text().splitlines()
        assert [int(r.split(",")[0]) for r in rows] == [200, 300, 400]

    def test_an_experiment_name_that_is_a_path_is_refused(self):
        with pytest.raises(ConfigError, match="logger.exp_name='../x' is invalid"):
            check_config(make_cfg(*RUN, "logger.exp_name=../x"))


class TestReaders:
    """Every reader of a run directory, not only training, refuses links out of it."""

    def test_a_linked_mlflow_database_is_never_opened(self, run, tmp_path):
        """The probe's attack: with no CSV metrics, ``read_scalar`` opened ``mlflow.db``
        through a planted link and MLflow wrote its tables into the linked database."""
        marker = tmp_path / "app.db"
        with sqlite3.connect(marker) as db:
            db.execute("CREATE TABLE users (name TEXT)")
            db.execute("INSERT INTO users VALUES ('alice')")
        before = marker.read_bytes()
        shutil.rmtree(run / "ddpg")
        (run / "mlflow.db").symlink_to(marker)
        for read in (lambda: read_scalar(run, "eval/return"), lambda: train_seconds(run)):
            with pytest.raises(UnsafeRunDirectory, match="mlflow.db is a symbolic link"):
                read()
        assert marker.read_bytes() == before

    def test_a_linked_metric_file_is_not_read(self, run, tmp_path):
        outside = tmp_path / "secret.csv"
        outside.write_text("100,42.0\n")
        csv = run / "ddpg" / "scalars" / "eval" / "return.csv"
        csv.unlink()
        csv.symlink_to(outside)
        for read in (lambda: read_scalar(run, "eval/return"), lambda: relogged(run, "eval/*")):
            with pytest.raises(UnsafeRunDirectory, match="return.csv is a symbolic link"):
                read()

    def test_load_policy_and_the_saved_config_refuse_a_link_out(self, run, tmp_path):
        (tmp_path / "outside").mkdir()
        (run / "notes").symlink_to(tmp_path / "outside")
        with pytest.raises(UnsafeRunDirectory, match="notes is a symbolic link"):
            load_policy(run)
        with pytest.raises(UnsafeRunDirectory, match="notes is a symbolic link"):
            config_for_resume(run, [f"resume={run}"], defaults())
        (run / "notes").unlink()
        (run / "notes").symlink_to(run / "checkpoints")  # a link that stays inside is fine
        load_policy(run)


class TestLoadPolicy:
    """What a loaded policy rests on is checked before it is built or returned."""

    def test_an_edited_width_is_refused_before_anything_is_allocated(self, run, monkeypatch):
        """The probe's 200,000-unit actor asked for 160 GB; the check comes first."""
        edit_config(run, **{"network.actor_cells": 200_000})
        built = []
        monkeypatch.setattr("torchrl_rave.recipe.agent.make_agent",
                            lambda *a, **k: built.append(1))  # fmt: skip
        with pytest.raises(DamagedCheckpoint, match="network.actor_cells=200000 is the size "
                           "of no tensor of the checkpoint"):  # fmt: skip
            load_policy(run)
        assert built == []

    def test_nan_weights_are_named(self, run):
        for checkpoint in RunCheckpoint(run).checkpoints():
            state = component(checkpoint, "policy") / "state"
            weight = state / "tensor_00000000.memmap"  # the first layer's weight
            weight.write_bytes(b"\xff" * weight.stat().st_size)  # float32 NaN
            rechecksum(checkpoint)
        with pytest.raises(DamagedCheckpoint, match="checkpoint-0+300: .*weight holds NaN or inf"):
            load_policy(run)

    def test_a_saved_config_without_its_env_is_refused(self, run):
        for checkpoint in RunCheckpoint(run).checkpoints():
            path = component(checkpoint, "config") / "value.json"
            cfg = json.loads(path.read_text())
            del cfg["env"]
            path.write_text(json.dumps(cfg))
            rechecksum(checkpoint)
        with pytest.raises(DamagedCheckpoint, match="saved config lacks \\['env'\\]"):
            load_policy(run)

    def test_a_malformed_saved_config_names_its_checkpoint(self, run):
        for checkpoint in RunCheckpoint(run).checkpoints():
            (component(checkpoint, "config") / "value.json").write_text("{not json")
            rechecksum(checkpoint)
        with pytest.raises(DamagedCheckpoint, match="checkpoint-0+300: its 'config' component "
                           "is unreadable"):  # fmt: skip
            load_policy(run)


class TestSavedConfig:
    def test_a_saved_interpolation_is_never_resolved(self, run, tmp_path, monkeypatch):
        """The probe's attack: a saved ``logger.exp_name: ${oc.env:TOKEN}`` wrote the
        user's environment variable into the run directory on resume."""
        monkeypatch.setenv("PROBE_TOKEN", "s3cret-value")
        edit_config(run, **{"logger.exp_name": "${oc.env:PROBE_TOKEN}"})
        with pytest.raises(UntrustedRunConfig, match="logger.exp_name='\\$\\{oc.env:PROBE_T"):
            config_for_resume(run, [f"resume={run}"], defaults())
        for trust in (False, True):  # an interpolation is refused whatever the trust
            with pytest.raises(UntrustedRunConfig, match="an interpolation"):
                load_policy(run, trust=trust)
        more = [f"resume={run}", "collector.total_frames=400"]
        with pytest.raises(UntrustedRunConfig, match="an interpolation"):
            rave_mujoco.train(make_cfg(*RUN, *more), str(run))
        found = [p for p in run.rglob("*") if "s3cret" in p.name or (
                 p.is_file() and b"s3cret" in p.read_bytes())]  # fmt: skip
        assert found == []
        # the caller's own value replaces the saved one
        cfg = config_for_resume(run, [*more, "logger.exp_name=ddpg"], defaults())
        assert cfg.logger.exp_name == "ddpg"

    def test_a_saved_remote_logger_is_not_contacted(self, run):
        edit_config(run, **{"logger.backend": "wandb", "logger.project": "someone-elses"})
        with pytest.raises(UntrustedRunConfig, match="logger.backend='wandb', which logs in "
                           "to W&B and writes to its project 'someone-elses'"):  # fmt: skip
            config_for_resume(run, [f"resume={run}"], defaults())
        with pytest.raises(UntrustedRunConfig, match="logger.backend"):
            load_agent(run)
        cfg = config_for_resume(run, [f"resume={run}", "logger.backend=csv"], defaults())
        assert cfg.logger.backend == "csv"

    def test_a_module_env_name_is_not_imported_by_load_policy(self, run, tmp_path, monkeypatch):
        marker = tmp_path / "imported"
        (run / "evilmod.py").write_text(f"import os\nos.mkdir({str(marker)!r})\n")
        edit_config(run, **{"env.name": "evilmod:Hopper-v5"})
        monkeypatch.chdir(run)
        monkeypatch.syspath_prepend(str(run))  # as `cd run && python -c ...` would have it
        with pytest.raises(UntrustedRunConfig, match="env.name='evilmod:Hopper-v5', which "
                           "imports the module 'evilmod'"):  # fmt: skip
            load_policy(".")
        assert not marker.exists()
        # trust=True is the caller's word: then the module is imported
        load_policy(".", trust=True)
        assert marker.exists()

    def test_a_module_env_name_is_not_imported_by_resume(self, run, tmp_path):
        edit_config(run, **{"env.name": "evilmod:Hopper-v5"})
        with pytest.raises(UntrustedRunConfig, match="Pass the key on the command line"):
            config_for_resume(run, [f"resume={run}"], defaults())
        # passed again by the caller, it is the caller's value
        cfg = config_for_resume(run, [f"resume={run}", "env.name=Hopper-v5"], defaults())
        assert cfg.env.name == "Hopper-v5"

    def test_a_saved_model_file_is_not_opened(self, run):
        edit_config(run, **{"env.kwargs": {"xml_file": "/etc/hostname"}})
        with pytest.raises(UntrustedRunConfig, match="env.kwargs.xml_file='/etc/hostname'"):
            load_agent(run)
        with pytest.raises(UntrustedRunConfig, match="env.kwargs.xml_file"):
            config_for_resume(run, [f"resume={run}"], defaults())
        cfg = config_for_resume(run, [f"resume={run}", "env.kwargs=null"], defaults())
        assert cfg.env.kwargs is None

    def test_a_saved_curriculum_of_file_names_is_not_followed(self, run):
        edit_config(run, **{"curriculum.kwarg": "xml_file", "curriculum.stages": ["/etc/hostname"],
                            "curriculum.thresholds": []})  # fmt: skip
        with pytest.raises(UntrustedRunConfig, match="curriculum.stages=\\['/etc/hostname'\\]"):
            config_for_resume(run, [f"resume={run}"], defaults())

    def test_a_saved_ray_address_is_not_joined(self, run):
        edit_config(run, **{"ray.address": "127.0.0.1:9", "collector.backend": "ray"})
        with pytest.raises(UntrustedRunConfig, match="ray.address='127.0.0.1:9', which joins"):
            config_for_resume(run, [f"resume={run}"], defaults())
        # load_policy connects nowhere, whatever the config says
        load_policy(run)

    def test_an_unreachable_ray_address_fails_fast_by_name(self, tmp_path):
        """The probe's resume hung for more than 300 s on an unreachable address. A real
        closed port on the loopback range; the whole run must fail within seconds."""
        started = time.monotonic()
        with pytest.raises(ConnectionError, match="no Ray cluster answers at ray.address"):
            reach_ray_address("127.0.0.1:9", timeout_s=5)
        cfg = make_cfg(*RUN, "collector.backend=ray", "collector.num_workers=1",
                       "ray.address=127.0.0.1:9", "ray.worker_cpus=1")  # fmt: skip
        with pytest.raises(ConnectionError, match="127.0.0.1:9"):
            rave_mujoco.train(cfg, str(tmp_path / "run"))
        assert time.monotonic() - started < 60


def test_a_pickle_is_what_the_probe_used(tmp_path):
    """The planted entry really runs code when tensordict loads it with its defaults: the
    tests above would see it if a load path reached it."""
    marker = tmp_path / "ran"
    TensorDict(w=torch.zeros(2)).memmap(tmp_path / "td")
    plant_pickle(tmp_path / "td", marker)
    with pytest.warns(FutureWarning):
        TensorDict.load_memmap(tmp_path / "td")
    assert marker.exists()


def test_a_garbage_mlflow_store_is_named(run):
    """The probe's garbage ``mlflow.db`` ended in an SQLAlchemy traceback."""
    shutil.rmtree(run / "ddpg")
    (run / "mlflow.db").write_bytes(b"garbage" * 100)
    with pytest.raises(ValueError, match="mlflow.db is not an SQLite database"):
        read_scalar(run, "eval/return")
    assert (run / "mlflow.db").read_bytes() == b"garbage" * 100


def test_a_ray_address_where_something_else_listens_fails_fast_by_name():
    """The probe's resume hung past ``collector.timeout_s`` on a port where another
    service listened; a listener that accepts and says nothing stands in for it."""
    import socket
    import threading

    server = socket.create_server(("127.0.0.1", 0))
    port = server.getsockname()[1]
    accepted = []  # held open: a listener that accepts and never answers
    threading.Thread(target=lambda: accepted.append(server.accept()), daemon=True).start()
    started = time.monotonic()
    with pytest.raises(ConnectionError, match=f"something listens at ray.address='127.0.0.1:"
                       f"{port}' but does not answer as a Ray cluster"):  # fmt: skip
        reach_ray_address(f"127.0.0.1:{port}", timeout_s=2)
    assert time.monotonic() - started < 10
    server.close()
