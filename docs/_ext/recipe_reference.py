"""Sphinx directives that render the recipe's reference tables from the library itself, so
that no key, default or metric is written down twice:

- ``.. recipe-keys::`` every key of :mod:`torchrl_rave.recipe.schema`, its type, its
  default (the ``cpu`` preset), the ``paper`` preset's value where it differs, the rule its
  value must meet and its help text;
- ``.. recipe-metrics::`` every metric of :data:`torchrl_rave.recipe.metrics.METRICS`;
- ``.. update-cost::`` the update-throughput figures of ``benchmarks/update_throughput.json``.
"""

from __future__ import annotations

import re
import typing
from dataclasses import MISSING

from docutils.parsers.rst import Directive
from docutils.parsers.rst import Parser as RSTParser
from docutils.utils import new_document
from omegaconf import OmegaConf


def _rst_inline(text: str) -> str:
    """Markdown-style inline code (`x`) as RST literals (``x``)."""
    return re.sub(r"(?<!`)`([^`]+)`(?!`)", r"``\1``", text)


def _literal(value) -> str:
    if value is None:
        return "``null``"
    if isinstance(value, str):
        return f'``"{value}"``' if value == "" else f"``{value}``"
    if isinstance(value, float) and value >= 1e5:
        return f"``{value:.0e}``"
    return f"``{value}``"


def _type_name(tp) -> str:
    text = tp if isinstance(tp, str) else getattr(tp, "__name__", str(tp))
    return text.replace("typing.", "").replace(" | None", " or null")


def _preset_value(preset: dict, dotted: str):
    node = preset
    for part in dotted.split("."):
        if not isinstance(node, dict) or part not in node:
            return MISSING
        node = node[part]
    return node


def _list_table(header: list[str], rows: list[list[str]], widths: str) -> list[str]:
    lines = [".. list-table::", "   :header-rows: 1", f"   :widths: {widths}", ""]
    for row in [header, *rows]:
        lines.append(f"   * - {row[0]}")
        lines.extend(f"     - {cell}" for cell in row[1:])
    return lines


class _TableDirective(Directive):
    has_content = False

    def lines(self) -> list[str]:
        raise NotImplementedError

    def run(self):
        # parsed as reStructuredText whatever the page's own markup (MyST pages included)
        settings = self.state.document.settings
        doc = new_document("recipe_reference", settings)
        RSTParser().parse("\n".join(self.lines()), doc)
        return list(doc.children)


class RecipeKeys(_TableDirective):
    def lines(self) -> list[str]:
        from torchrl_rave.recipe.schema import (
            PRESET_ALGORITHMS,
            PRESETS,
            RecipeConfig,
            schema_fields,
        )

        defaults = OmegaConf.structured(RecipeConfig)
        hints: dict[str, typing.Any] = {}
        rows = []
        for dotted, f in schema_fields():
            default = OmegaConf.select(defaults, dotted)
            default = OmegaConf.to_container(default) if OmegaConf.is_config(default) else default
            paper = _preset_value(PRESETS["paper"], dotted)
            mujoco = _preset_value(PRESETS["mujoco"], dotted)
            mujoco = "" if mujoco is MISSING else _literal(mujoco)
            for algorithm, own in PRESET_ALGORITHMS["mujoco"].items():
                value = _preset_value(own, dotted)
                if value is not MISSING:
                    mujoco = f"{mujoco} ({algorithm}: {_literal(value)})".strip()
            rule = f.metadata.get("rule")
            tp = hints.get(dotted, f.type)
            meaning = _rst_inline(f.metadata["help"])
            if rule is not None:
                meaning += f". *Allowed:* {_rst_inline(rule.expected)}."
            rows.append(
                [
                    f"``{dotted}`` ({_type_name(tp)})",
                    _literal(default),
                    "" if paper is MISSING else _literal(paper),
                    mujoco,
                    meaning,
                ]
            )
        header = ["key (type)", "default (``cpu``)", "``paper``", "``mujoco``", "meaning"]
        return _list_table(header, rows, "24 10 9 12 45")


class RecipeMetrics(_TableDirective):
    def lines(self) -> list[str]:
        from torchrl_rave.recipe.metrics import METRICS

        rows = [[f"``{name}``", _rst_inline(meaning)] for name, meaning in METRICS.items()]
        return _list_table(["metric", "meaning"], rows, "30 70")


class UpdateCost(_TableDirective):
    """``.. update-cost:: default`` (or ``paper``): the update-throughput table of
    ``benchmarks/update_throughput.json``, with each row's time as a multiple of the
    recipe's ``ddpg`` update; ``.. update-cost:: ratios``: the run's time ratios at both
    sizes, as the benchmark computed them."""

    required_arguments = 1

    def lines(self) -> list[str]:
        import json
        from pathlib import Path

        path = Path(__file__).resolve().parents[2] / "benchmarks" / "update_throughput.json"
        data = json.loads(path.read_text())
        kind = self.arguments[0]
        if kind == "ratios":
            paper = {k: v for k, v in data.get("paper", {}).items() if isinstance(v, float)}
            body = [
                [f"``{name}``", f"{v:.2f}", sizes]
                for sizes, ratios in (("default", data["default"]["ratios"]), ("paper", paper))
                for name, v in ratios.items()
            ]
            return _list_table(
                ["ratio (of times per update, unless it says FLOPs)", "value", "sizes"],
                body,
                "60 20 20",
            )
        if kind == "default":
            rows, base, time_key, unit, digits = (
                data["default"]["rows"],
                "ours: ddpg",
                "ms_per_update",
                "ms",
                2,
            )
        elif kind == "paper":
            rows = {k: v for k, v in data["paper"].items() if isinstance(v, dict)}
            base, time_key, unit, digits = "ddpg", "s_per_500_batches", "s / 500 batches", 1
        else:
            raise self.error(f"update-cost takes default, paper or ratios, not {kind!r}")
        body = [
            [name, f"{r[time_key]:.{digits}f}", f"{r[time_key] / rows[base][time_key]:.1f}",
             f"{r['gflop_per_update']:.3f}", f"{100 * r['fraction_of_peak']:.1f} %"]
            for name, r in rows.items()
        ]  # fmt: skip
        header = ["update", unit, "x ours: ddpg", "GFLOP", "of matmul peak"]
        lines = _list_table(header, body, "34 14 14 14 14")
        lines += ["", f"Measured on {data['device']}, torch {data['torch']}, "
                  f"{data['threads']} threads; matmul peak {data['matmul_peak_gflops']:.0f} "
                  "GFLOP/s (``benchmarks/update_throughput.json``)."]  # fmt: skip
        if data.get("commit"):
            lines[-1] += f" Command: ``{data['command']}``, at commit ``{data['commit']}``."
        return lines


def setup(app):
    app.add_directive("recipe-keys", RecipeKeys)
    app.add_directive("recipe-metrics", RecipeMetrics)
    app.add_directive("update-cost", UpdateCost)
    return {"parallel_read_safe": True, "parallel_write_safe": True}
