"""What ``m3t score`` reports (:class:`ScoreReport`: the table, CSV, JSON and the files ``--out`` writes) and the
steps every input kind shares: choosing definitions and pairing clip ids."""
from __future__ import annotations

import csv
import io
import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

from m3t.atomic import write_json, write_text
from m3t.scoring.poses import ScoreInputError


@dataclass
class ScoreReport:
    """What :func:`score` measured: one value per metric (keys carry their definition's name), how many clips
    each definition averaged, every clip's own values, and the clips left out with their reason."""

    kind: str  # "pose" or "text"
    prediction: str
    reference: str
    metrics: dict[str, float] = field(default_factory=dict)
    definition_of: dict[str, str] = field(default_factory=dict)  # metric -> definition
    clips_scored: dict[str, int] = field(default_factory=dict)  # definition -> clips in its values
    per_clip: list[dict] = field(default_factory=list)  # {"clip", "definition", "metric", "value"}
    unscored: list[dict] = field(default_factory=list)  # {"clip", "definition", "reason"}
    # back-translations: {"clip", "language", "hypothesis", "reference"}
    sentences: list[dict] = field(default_factory=list)
    paired: int = 0  # clips present on both sides
    notes: list[str] = field(default_factory=list)

    def rows(self) -> list[tuple[str, str, float, int]]:
        """(definition, metric, value, clips) in the order measured."""
        return [(self.definition_of[k], k, v, self.clips_scored[self.definition_of[k]]) for k, v in self.metrics.items()]

    def table(self) -> str:
        """The terminal table: one line per metric, then the unscored clips."""
        lines = [f"m3t score ({self.kind}): {self.prediction} against {self.reference}; {self.paired} clips paired",
                 f"{'definition':<11} {'metric':<28} {'value':>12} {'clips':>6}"]
        lines += [f"{d:<11} {m:<28} {_number(v):>12} {n:>6}" for d, m, v, n in self.rows()]
        if self.unscored:
            lines.append(f"not scored ({len(self.unscored)}):")
            lines += [f"  {u['clip']} [{u['definition']}]: {u['reason']}" for u in self.unscored]
        lines += self.notes
        return "\n".join(lines)

    def csv(self) -> str:
        """The table as CSV: definition, metric, value, clips."""
        return _csv(("definition", "metric", "value", "clips"), self.rows())

    def as_json(self) -> dict:
        return {"kind": self.kind, "prediction": self.prediction, "reference": self.reference,
                "paired": self.paired, "clips_scored": self.clips_scored,
                "metrics": {k: _finite_or_none(v) for k, v in self.metrics.items()},
                "definition_of": self.definition_of, "unscored": self.unscored, "notes": self.notes,
                "per_clip": [dict(r, value=_finite_or_none(r["value"])) for r in self.per_clip],
                "sentences": self.sentences}

    def write(self, out: str | Path) -> list[Path]:
        """``score.json`` (everything), ``score.csv`` (the table), ``clips.csv`` (per clip), ``unscored.csv`` and,
        with back-translations, ``sentences.csv`` into folder ``out``, each written whole or not at all."""
        out = Path(out)
        out.mkdir(parents=True, exist_ok=True)
        files = {"score.json": None,
                 "score.csv": self.csv(),
                 "clips.csv": _csv(("clip", "definition", "metric", "value"),
                                   [(r["clip"], r["definition"], r["metric"], r["value"]) for r in self.per_clip]),
                 "unscored.csv": _csv(("clip", "definition", "reason"),
                                      [(u["clip"], u["definition"], u["reason"]) for u in self.unscored])}
        if self.sentences:
            files["sentences.csv"] = _csv(("clip", "language", "hypothesis", "reference"),
                                          [tuple(r.values()) for r in self.sentences])
        written = []
        for name, text in files.items():
            path = out / name
            if text is None:
                write_json(path, self.as_json())
            else:
                write_text(path, text)
            written.append(path)
        return written


def _number(v: float) -> str:
    return f"{v:.4f}" if math.isfinite(v) else str(v)


def _finite_or_none(v: float) -> float | None:
    return v if math.isfinite(v) else None


def _csv(header: Sequence[str], rows: Iterable[Sequence]) -> str:
    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    writer.writerow(header)
    writer.writerows(rows)
    return buffer.getvalue()


def check_definitions(definitions: Sequence[str] | None, known: Sequence[str], kind: str) -> list[str]:
    """The definitions asked for (default: every one in ``known``); an error naming the choices otherwise."""
    chosen = list(known if definitions is None else definitions)
    unknown = [d for d in chosen if d not in known]
    if unknown or not chosen:
        raise ScoreInputError(f"definitions {unknown or chosen} do not apply to {kind} inputs; choose from "
                              f"{', '.join(known)}")
    return chosen


def pairing(pred: dict, ref: dict, report: ScoreReport, what: str) -> list[str]:
    """Clip ids on both sides (in the reference's order); the others listed in ``report.unscored``. Error when
    none pairs; ``what`` names a clip's kind in the reasons (".pose file", "line", "id", "clip")."""
    both = [k for k in ref if k in pred]
    for k in ref:
        if k not in pred:
            report.unscored.append({"clip": k, "definition": "all", "reason": f"no prediction (no {what} {k!r} "
                                    f"under {report.prediction})"})
    for k in pred:
        if k not in ref:
            report.unscored.append({"clip": k, "definition": "all", "reason": f"no reference (no {what} {k!r} "
                                    f"under {report.reference})"})
    if not both:
        raise ScoreInputError(f"no clip id is on both sides: {len(pred)} predictions ({_examples(pred)}) and "
                              f"{len(ref)} references ({_examples(ref)}); name each prediction as its reference")
    report.paired = len(both)
    return both


def _examples(ids: Iterable[str]) -> str:
    ids = list(ids)
    return ", ".join(repr(i) for i in ids[:3]) + (", ..." if len(ids) > 3 else "") if ids else "none"
