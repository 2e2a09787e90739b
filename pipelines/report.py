"""The evaluation report: every stage's rows merged into one table, as markdown and as a plot."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from matplotlib.figure import Figure

REAL = "Real"
PARAPHRASE = "@paraphrase"  # pipelines.evaluation.PARAPHRASE: rows answering the held-out paraphrases

COLUMNS = [  # (metrics.json key, report header, decimals)
    ("R_precision_top1", "R@1 ↑", 3), ("R_precision_top2", "R@2 ↑", 3), ("R_precision_top3", "R@3 ↑", 3),
    ("FID", "FID ↓", 3), ("MM_Dist", "MM-Dist ↓", 3), ("Diversity", "Diversity →", 3),
    ("MultiModality", "MModality ↑", 3), ("NFE", "NFE", 0), ("AITS_s", "AITS (s) ↓", 4),
    ("ms_per_frame", "ms/frame ↓", 3),
    ("MPJPE_mm", "MPJPE (mm) ↓", 1), ("skating_ratio", "Skate ↓", 3), ("penetration_mm", "Penetrate (mm) ↓", 2),
    ("floating_mm", "Float (mm) ↓", 2),
]
CONTROL_COLUMNS = [  # rows with control errors get a second, OmniControl-style table
    ("traj_err_50cm", "Traj. err (50 cm) ↓", 3), ("loc_err_50cm", "Loc. err (50 cm) ↓", 3),
    ("traj_err_20cm", "Traj. err (20 cm) ↓", 3), ("loc_err_20cm", "Loc. err (20 cm) ↓", 3),
    ("avg_err_m", "Avg. err (m) ↓", 3), ("FID", "FID ↓", 3), ("R_precision_top3", "R@3 ↑", 3),
    ("AITS_s", "AITS (s) ↓", 4),
]

DETAIL_COLUMNS = [  # reconstruction rows (they have an MPJPE): what of the real motions' actions survives
    ("MPJPE_mm", "MPJPE (mm) ↓", 1), ("path_err_m", "Path err. (m) ↓", 3), ("turn_kept", "Turns kept ↑", 3),
    ("kick_kept", "Kicks kept ↑", 3), ("wave_kept", "Wave swings kept ↑", 3), ("jumps_kept", "Jump counts kept ↑", 3),
    ("action_accuracy", "Action acc. ↑", 3),
]
ACTION_COLUMNS = [  # action-to-motion rows (they have an Accuracy) get their own table: recogniser features
    ("Accuracy", "Accuracy ↑", 3), ("FID", "FID ↓", 3), ("Diversity", "Diversity →", 3),
    ("MultiModality", "MModality →", 3), ("NFE", "NFE", 0),
]
SPEED_COLUMNS = [  # the eval_speed stage's rows (stages/speed.py): timed side by side in one process
    ("ms_per_frame", "ms/frame ↓", 3), ("AITS_s", "AITS (s) ↓", 4), ("NFE", "NFE", 0), ("params_M", "Params (M)", 2),
    ("speedup", "Speed-up ↑", 1),
]
PARAPHRASE_COLUMNS = [  # Real, the headline rows and their paraphrase twins (they have an action_accuracy)
    ("R_precision_top1", "R@1 ↑", 3), ("R_precision_top3", "R@3 ↑", 3), ("FID", "FID ↓", 3),
    ("MM_Dist", "MM-Dist ↓", 3), ("Diversity", "Diversity →", 3), ("action_accuracy", "Action acc. ↑", 3),
]


def merge_tables(tables: list[dict[str, dict[str, float]]]) -> dict[str, dict[str, float]]:
    """One table from the stages' tables, in order; a row name in two tables is an error."""
    merged: dict[str, dict[str, float]] = {}
    for table in tables:
        clash = sorted(set(merged) & set(table))
        if clash:
            raise ValueError(f"row(s) {clash} come from two evaluation stages")
        merged |= table
    return merged


def _cell(row: dict[str, float], key: str, decimals: int) -> str:
    if key not in row:
        return "–"
    text = f"{row[key]:.{decimals}f}"
    return f"{text} ± {row[key + '_ci']:.{decimals}f}" if f"{key}_ci" in row else text


def _name(name: str, row: dict[str, float]) -> str:
    """The row's name, marked when it was evaluated on a subset of each draw (``eval_items``) and of the
    replications (``eval_replications``)."""
    marks = ([f"†{int(row['eval_items'])}"] if "eval_items" in row else []) + (
        [f"{int(row['eval_replications'])} rep."] if "eval_replications" in row else [])
    return f"{name} ({', '.join(marks)})" if marks else name


@dataclass(frozen=True)
class Section:
    """One table of the report: its heading (None for the main table), rows and columns."""

    heading: str | None
    rows: dict[str, dict[str, float]]
    columns: list[tuple[str, str, int]]


def report_title(meta: dict[str, Any]) -> str:
    """What was evaluated: the dataset, its test items and the replications, and the GPU the networks ran on
    when they did (``sample.device``; its timing columns are that GPU's)."""
    device = meta.get("device", "cpu")
    where = "" if device == "cpu" else f", networks on {device}"
    return (f"Evaluation on {meta['dataset']} ({meta['test_items']} test items, {meta['replications']} "
            f"replications{where})")


def report_sections(table: dict[str, dict[str, float]], speed: dict[str, dict[str, float]] | None = None
                    ) -> list[Section]:
    """The paper-style table, then the reconstruction-detail table if any row has one, then the control
    table if any row has one, then the paraphrase table if any
    row answered paraphrases, then the action-to-motion table if any row is action-conditioned (paraphrase
    and action rows are not in the first table), then the side-by-side ``speed`` table if it has rows."""
    actions = {name: row for name, row in table.items() if "Accuracy" in row}
    texts = {name: row for name, row in table.items() if name not in actions and not name.endswith(PARAPHRASE)}
    reconstructions = {name: row for name, row in texts.items() if "path_err_m" in row}
    semantic = {name: row for name, row in table.items() if "action_accuracy" in row and name not in reconstructions}
    sections = [Section(None, texts, COLUMNS)]
    if reconstructions:
        sections.append(Section("Reconstruction detail (of the test motions that turn by 135° or more, kick, wave "
                                "or jump, the fraction whose reconstruction keeps it, judged on the joints: "
                                "data/joint_measures.py; Action acc.: the action recogniser on the reconstructed "
                                "labelled single-action items)", reconstructions, DETAIL_COLUMNS))
    controlled = {name: row for name, row in texts.items() if "avg_err_m" in row}
    if controlled:
        sections.append(Section("Trajectory control (errors on the controlled keyframes of the test crops' own "
                                "joints)", controlled, CONTROL_COLUMNS))
    if any(name.endswith(PARAPHRASE) for name in semantic):
        sections.append(Section("Held-out paraphrases (<row>@paraphrase: the same test items asked for in words "
                                "no training caption uses, judged against the original captions; Action acc.: the "
                                "action recogniser on the labelled single-action items)", semantic, PARAPHRASE_COLUMNS))
    if actions:
        sections.append(Section("Action-to-motion (the labelled single-action test motions; FID, Diversity and "
                                "MultiModality in the action recogniser's features, not comparable with the table "
                                "above)", actions, ACTION_COLUMNS))
    if speed:
        sections.append(Section("Inference speed side by side (timed in one process, batch 1, warm, in rounds of "
                                "alternating order: stage eval_speed; Speed-up: the slowest row's ms/frame over the "
                                "row's; Params: the row's networks, the shared text encoder not counted)",
                                speed, SPEED_COLUMNS))
    return sections


def report_notes(table: dict[str, dict[str, float]]) -> list[str]:
    """The notes under the tables: what →, ± and AITS mean, and (†K) when a row has ``eval_items``."""
    notes = ["→: closer to Real (Real-action) is better. ± is 1.96·std/√R over replications. "
             "AITS: seconds per sentence, batch 1, warm, loading and text encoding excluded."]
    if any("eval_items" in row and "Accuracy" not in row for row in table.values()):
        notes.append("(†K): evaluated on the first K captions of each replication's draw, not the whole test set "
                     "(too slow): its FID (biased upward by few samples) and Diversity compare only with rows of "
                     "the same K; no MultiModality.")
    if any("eval_replications" in row for row in table.values()):
        notes.append("(R rep.), (†K, R rep.): evaluated in the first R replications only (no ± when R = 1).")
    return notes


def table_cells(section: Section) -> tuple[list[str], list[list[str]]]:
    """A section's header and its rows of cells as text, the same text as in the markdown tables."""
    header = ["Method", *(h for _, h, _ in section.columns)]
    rows = [[_name(name, row), *(_cell(row, k, d) for k, _, d in section.columns)]
            for name, row in section.rows.items()]
    return header, rows


def _markdown_table(section: Section) -> list[str]:
    header, rows = table_cells(section)
    return ["| " + " | ".join(header) + " |", "|---" * len(header) + "|"] + [
        "| " + " | ".join(cells) + " |" for cells in rows]


def report_markdown(table: dict[str, dict[str, float]], meta: dict[str, Any],
                    speed: dict[str, dict[str, float]] | None = None) -> str:
    """The report as markdown: title, the tables of :func:`report_sections` (mean ± 95% CI over
    replications) and the notes."""
    lines = [f"# {report_title(meta)}"]
    for section in report_sections(table, speed):
        if section.heading is not None:
            lines += ["", f"## {section.heading}"]
        lines += ["", *_markdown_table(section)]
    for note in report_notes(table):
        lines += ["", note]
    return "\n".join(lines) + "\n"


def plot_fid_vs_time(table: dict[str, dict[str, float]], path: Path) -> None:
    """FID against AITS for every timed row; the Real row's FID as a dashed line."""
    fig = Figure(figsize=(6, 4))
    ax = fig.subplots()
    for name, row in table.items():
        if "AITS_s" in row:
            ax.scatter(row["AITS_s"], row["FID"], s=40)
            ax.annotate(_name(name, row), (row["AITS_s"], row["FID"]), textcoords="offset points", xytext=(5, 5))
    if REAL in table:
        ax.axhline(table[REAL]["FID"], linestyle="--", color="grey", label="Real")
        ax.legend()
    ax.set_xscale("log")
    ax.set_xlabel("AITS (s per sentence, log)")
    ax.set_ylabel("FID")
    ax.set_title("FID vs inference time")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
