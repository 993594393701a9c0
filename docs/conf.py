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
    "myst_parser",
]

source_suffix = {".rst": "restructuredtext", ".md": "markdown"}
exclude_patterns = ["_build", "figures/*.md", "README.md"]
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
# names from torch, torchrl, tensordict and gymnasium in signatures are not ours to resolve
nitpicky = False

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


def setup(app):
    app.connect("autodoc-process-signature", _init_signature)
    return _load_local_extension("recipe_reference").setup(app)
