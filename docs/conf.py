"""Sphinx configuration of the torchrl-rave documentation.

Build: ``.venv/bin/python -m sphinx -E -W --keep-going -b html docs docs/_build/html``
(the README's test command runs it; ``-W`` turns every warning into an error).
"""

from __future__ import annotations

import importlib.util
from pathlib import Path

import torchrl_rave

DOCS = Path(__file__).resolve().parent


def _load_local_extension(name: str):
    """``docs/_ext/<name>.py``, loaded from its file (no edit of ``sys.path``)."""
    spec = importlib.util.spec_from_file_location(name, DOCS / "_ext" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


project = "torchrl-rave"
author = "torchrl-rave maintainers"
copyright = "2026, torchrl-rave maintainers"
release = version = torchrl_rave.__version__

extensions = [
    "sphinx.ext.autodoc",
    "sphinx.ext.autosummary",
    "sphinx.ext.napoleon",
    "sphinx.ext.mathjax",
    "sphinx.ext.viewcode",
    "sphinx.ext.intersphinx",
    "myst_parser",
]

# TorchRL's and tensordict's names link to their documentation, through the inventories
# kept in docs/_inventories/ (its README says where each came from): the build reads them
# from disk and never goes to the network.
intersphinx_mapping = {
    "torchrl": ("https://docs.pytorch.org/rl/stable/", str(DOCS / "_inventories" / "torchrl.inv")),
    "tensordict": (
        "https://docs.pytorch.org/tensordict/0.14/",
        str(DOCS / "_inventories" / "tensordict.inv"),
    ),
}
intersphinx_timeout = 1

source_suffix = {".rst": "restructuredtext", ".md": "markdown"}
exclude_patterns = ["_build", "figures/*.md", "README.md", "_inventories"]
root_doc = "index"

# MyST: $...$ and $$...$$ math, heading anchors for cross-page links
myst_enable_extensions = ["dollarmath", "colon_fence", "deflist"]
myst_heading_anchors = 3

# autodoc: every public name, with its full signature and defaults
autodoc_default_options = {"members": True, "show-inheritance": True}
autodoc_member_order = "bysource"
autodoc_typehints = "signature"
autodoc_preserve_defaults = True
autodoc_class_signature = "mixed"
autodoc_inherit_docstrings = False
autosummary_generate = False
napoleon_google_docstring = True
napoleon_numpy_docstring = False
napoleon_use_rtype = False
add_module_names = False
python_use_unqualified_type_names = True

html_theme = "furo"
html_title = f"torchrl-rave {release}"
html_static_path = ["_static"]
html_css_files = ["tables.css"]
html_show_sourcelink = False


def _init_signature(app, what, name, obj, options, signature, return_annotation):
    """TorchRL's ``ValueEstimatorBase`` and ``LossModule`` define ``__new__(*args,
    **kwargs)``, which autodoc would show instead of ``__init__``'s arguments and
    defaults; show ``__init__``'s."""
    import inspect

    if what == "class" and signature in ("(*args, **kwargs)", "(*args, **kwargs) -> None"):
        try:  # the annotations as types, not as the strings `from __future__` leaves
            sig = inspect.signature(obj.__init__, eval_str=True)
        except Exception:  # noqa: BLE001 (a name only importable under TYPE_CHECKING)
            sig = inspect.signature(obj.__init__)
        params = list(sig.parameters.values())[1:]  # drop self
        return str(sig.replace(parameters=params, return_annotation=inspect.Signature.empty)), None
    return None


def _skip_keys_alias(app, what, name, obj, skip, options):
    """``default_keys`` is TorchRL's alias of a private dataclass; its keys are listed in
    the class's own docstring instead (:func:`_list_tensordict_keys`)."""
    return True if name == "default_keys" else None


def _list_tensordict_keys(app, what, name, obj, options, lines):
    """A class with TorchRL's ``default_keys`` gets its configurable keys, their defaults and
    their meanings (from the keys dataclass's ``Attributes:``) at the end of its docstring."""
    import dataclasses
    import re

    keys = getattr(obj, "default_keys", None) if what == "class" else None
    if keys is None or not dataclasses.is_dataclass(keys):
        return
    meaning, current = {}, None
    for line in (keys.__doc__ or "").split("Attributes:", 1)[-1].splitlines():
        match = re.match(r"\s+(\w+) \(NestedKey\): (.*)", line)
        if match:
            current = match.group(1)
            meaning[current] = match.group(2)
        elif current and line.strip():
            meaning[current] += " " + line.strip()
    lines += ["", ".. rubric:: Tensordict keys", "",
              "Renamed with ``set_keys(<name>=<key>)``; each default is the key read or written.", ""]  # fmt: skip
    for field in dataclasses.fields(keys):
        text = re.sub(r"\s*Defaults to .*$", "", meaning.get(field.name, "")).rstrip(".")
        lines.append(f"- ``{field.name}`` = ``{field.default!r}``: {text}.")
    lines.append("")


def setup(app):
    app.connect("autodoc-process-signature", _init_signature)
    app.connect("autodoc-skip-member", _skip_keys_alias)
    app.connect("autodoc-process-docstring", _list_tensordict_keys)
    return _load_local_extension("recipe_reference").setup(app)


# Nitpicky: every cross-reference to a name of ours must resolve. TorchRL's and tensordict's
# names resolve through intersphinx where their inventories hold them; the names of other
# packages (torch, whose inventory is not kept, gymnasium, omegaconf, ...) and the few
# TorchRL / tensordict names their inventories lack stay unlinked. They are listed here, so
# that a warning is a gap of our own.
nitpicky = True
napoleon_preprocess_types = True
napoleon_type_aliases = {
    "Tensor": "torch.Tensor",
    "TensorDictBase": "tensordict.TensorDictBase",
    "TensorDictModuleBase": "tensordict.nn.TensorDictModuleBase",
    "TensorDictModule": "tensordict.nn.TensorDictModule",
    "NestedKey": "tensordict.NestedKey",
    "LossModule": "torchrl.objectives.LossModule",
    "WorldModelEnsemble": "torchrl_rave.modules.WorldModelEnsemble",
    "WorldModelEnsembleLoss": "torchrl_rave.objectives.WorldModelEnsembleLoss",
}
nitpick_ignore_regex = [
    (
        r"py:.*",
        r"(torch|tensordict|torchrl|omegaconf|numpy|gymnasium|pathlib|collections|"
        r"typing|mujoco|hydra|matplotlib|ray)(\..*)?",
    ),
    (
        r"py:.*",
        r"(nn\.Module|Tensor|TensorDictBase|TensorDictModuleBase|TensorDictModule|"
        r"NestedKey|DEVICE_TYPING|EnvBase|Bounded|WeightUpdaterBase|WeightSyncScheme|"
        r"Literal\[.*|tuple\[.*|Callable|Sequence|Mapping|Path|EnvCreator|ExplorationType|"
        r"ReplayBuffer|argparse\..*|LossModule)",
    ),
    # napoleon splits a docstring's generic type on its commas (``Mapping[str, float]``)
    (r"py:class", r"(Sequence|Mapping|type|list|dict)\[.*|.*\]"),
]
