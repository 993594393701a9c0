"""``keep_freed_memory``: freed megabyte-sized blocks are reused without page faults, and
the recipe turns it on (its config key is checked)."""

from __future__ import annotations

import subprocess
import sys

import pytest
import rave_mujoco
from test_recipe import TINY, make_cfg

from torchrl_rave.recipe import memory
from torchrl_rave.recipe.config import check_config

# allocates and frees 2 MiB temporaries 100 times, then counts the page faults of 100 more.
# "plain" holds glibc's documented default thresholds fixed (128 KiB each; setting them
# turns off glibc's dynamic adjustment). Left dynamic, they rise after an early large free
# or not, depending on the heap's layout: a plain process faulted 1,500 to 50,000 pages
# over the loop in a dozen local runs, and none at all in one CI run.
FAULTS = """
import ctypes, resource, sys, torch
from torchrl_rave.recipe.memory import M_MMAP_THRESHOLD, M_TRIM_THRESHOLD, keep_freed_memory
if sys.argv[1] == "keep":
    kept = keep_freed_memory()
else:
    libc = ctypes.CDLL(None)
    kept = all(libc.mallopt(k, 128 * 1024) == 1 for k in (M_MMAP_THRESHOLD, M_TRIM_THRESHOLD))
x = torch.ones(512, 1024)
def loop():
    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    for _ in range(100):
        y = x * 2
        z = y + 1
    return resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before
loop()
print(kept, loop())
"""


def _faults(mode: str) -> tuple[str, int]:
    out = subprocess.run(
        [sys.executable, "-c", FAULTS, mode], capture_output=True, text=True, check=True
    ).stdout.split()
    return out[0], int(out[1])


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's malloc")
def test_freed_blocks_are_reused_without_page_faults():
    fixed, plain = _faults("plain")
    kept, faults = _faults("keep")
    assert fixed == "True"  # both mallopt calls took effect
    assert kept == "True"
    # held fixed, glibc maps every 2 MiB block and unmaps it when freed: each of the 200
    # faults all its 512 pages in again (left dynamic: 0 to 50,000 in all, run to run)
    assert plain >= 200 * 512
    assert faults < 50  # 200 blocks of 512 pages each, reused


def test_recipe_turns_it_on_and_checks_the_key(monkeypatch, tmp_path):
    calls = []
    monkeypatch.setattr(memory, "keep_freed_memory", lambda: calls.append(1))
    cfg = make_cfg(*TINY, "algorithm=ddpg", "collector.total_frames=200")
    rave_mujoco.train(cfg, str(tmp_path))
    assert calls == [1]
    rave_mujoco.train(make_cfg(*TINY, "algorithm=ddpg", "collector.total_frames=200",
                               "keep_freed_memory=false"), str(tmp_path / "off"))  # fmt: skip
    assert calls == [1]
    with pytest.raises(ValueError, match="keep_freed_memory='yes' is invalid"):
        check_config(make_cfg(*TINY, "keep_freed_memory=yes"))
