"""Suite-wide settings: one torch thread per pytest-xdist worker, longest tests first.

The suite runs on as many workers as the machine has cores (``-n auto`` in
pyproject.toml). Each worker is its own process; giving each one thread stops the
workers' thread pools from fighting over the same cores (the subprocesses a test
starts inherit ``OMP_NUM_THREADS``). ``-n 0`` runs everything in this process with
torch's default thread count.

Tests marked ``slow`` are moved to the front of the collection, so a worker starts
them at once and the other workers share out the rest meanwhile.
"""

import importlib
import os

import pytest


def pytest_configure(config):
    if os.environ.get("PYTEST_XDIST_WORKER"):
        os.environ["OMP_NUM_THREADS"] = "1"
        os.environ["MKL_NUM_THREADS"] = "1"
        import torch

        torch.set_num_threads(1)


def pytest_collection_modifyitems(config, items):
    items.sort(key=lambda item: item.get_closest_marker("slow") is None)  # stable: slow first


@pytest.fixture
def hide_modules(monkeypatch):
    """``hide_modules(*names)``: from then on ``importlib.import_module`` raises
    ImportError for those names, as if their package were not installed."""
    real = importlib.import_module

    def hide(*names: str) -> None:
        def import_module(name, *args):
            if name in names:
                raise ImportError(f"No module named {name!r}")
            return real(name, *args)

        monkeypatch.setattr(importlib, "import_module", import_module)

    return hide
