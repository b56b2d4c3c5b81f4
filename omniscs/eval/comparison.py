"""One picture per evaluation run: the models it evaluated side by side, from its ``evaluations`` rows.

A panel per task, split and scoring (detection all round or in the cameras' view; planning by UniAD's convention):
detection shows mAP, NDS and the AP of each class; planning the L2 (m) and the collision rate (%) at each horizon.
Each model is one colour of bars, so base against fine-tuned reads at a glance; a metric a model has no value for
(undefined, or its evaluation failed) is an empty slot marked "n/a", never a zero."""
from __future__ import annotations

import io
from pathlib import Path

import numpy as np

from omniscs.errors import ValidationError
from omniscs.storage import atomic_write_bytes

COLOURS = ("#4c72b0", "#dd8452", "#55a868", "#c44e52", "#8172b3", "#937860")
#: The planning convention drawn (UniAD's own: the value at each horizon); stp3's means stay in the catalog.
PLANNING_CONVENTION = "uniad"


def _panels(rows: list[dict]) -> dict[tuple[str, str, str], dict[str, dict[str, float | None]]]:
    """{(task, split, scoring): {bar label: {model id: value}}} of the rows worth drawing, in the rows' order."""
    panels: dict[tuple[str, str, str], dict[str, dict[str, float | None]]] = {}
    for r in rows:
        if r["status"] != "ok":
            continue
        if r["task"] == "detection" and r["metric"] in ("mAP", "NDS", "AP"):
            scoring = "in the cameras' view" if r["convention"] == "camera_view" else "all round"
            label = r["metric"] if r["metric"] != "AP" else f"AP {r['class_name']}"
        elif r["task"] == "planning" and r["convention"] in (PLANNING_CONVENTION, "") \
                and r["metric"] in ("L2", "collision"):  # '': an external job's printed table
            scoring = f"{r['convention'] or 'as printed'}: {'L2 (m)' if r['metric'] == 'L2' else 'collision (%)'}"
            label = r["horizon"]
        else:
            continue
        value = r["value"]
        if value is not None and r["metric"] != "L2":
            value = 100.0 * value  # AP in points, collision rates in %
        panels.setdefault((r["task"], r["split"], scoring), {}).setdefault(label, {})[r["model_id"]] = value
    return panels


def comparison_png(rows: list[dict], title: str = "") -> bytes:
    """The figure of ``rows`` (``evaluations`` records) as PNG bytes; a clear error when no row can be drawn."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    panels = _panels(rows)
    if not panels:
        raise ValidationError("no evaluation row to draw: every row failed, or none is a detection mAP/NDS/AP or a "
                              f"planning L2/collision ({PLANNING_CONVENTION} convention)")
    models = list(dict.fromkeys(r["model_id"] for r in rows if r["status"] == "ok"))
    cols = min(len(panels), 2)
    nrows = -(-len(panels) // cols)
    fig, axes = plt.subplots(nrows, cols, figsize=(7 * cols, 3.6 * nrows), squeeze=False)
    for ax in axes.flat[len(panels):]:
        ax.set_visible(False)
    width = 0.8 / len(models)
    for ax, ((task, split, scoring), bars) in zip(axes.flat, panels.items()):
        labels = list(bars)
        x = np.arange(len(labels))
        for j, model in enumerate(models):
            values = [bars[k].get(model) for k in labels]
            pos = x + (j - (len(models) - 1) / 2) * width
            ax.bar(pos, [np.nan if v is None else v for v in values], width, label=model,
                   color=COLOURS[j % len(COLOURS)])
            for p, v in zip(pos, values):
                if v is None:
                    ax.text(p, 0, "n/a", ha="center", va="bottom", fontsize=7, color="#555555")
        ax.set_xlim(-0.5, len(labels) - 0.5)
        ax.set_xticks(x, labels, rotation=30 if task == "detection" else 0, ha="right" if task == "detection"
                      else "center", fontsize=8)
        ax.set_ylabel("points" if task == "detection" else scoring.split(": ")[-1])
        ax.set_title(f"{task}, {split} ({scoring})", fontsize=9)
        ax.legend(fontsize=7)
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=90)
    plt.close(fig)
    return buffer.getvalue()


def write_comparison(rows: list[dict], out_png: str | Path, title: str = "") -> Path:
    """``comparison_png`` written atomically to ``out_png``."""
    out = Path(out_png)
    out.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_bytes(out, comparison_png(rows, title))
    return out
