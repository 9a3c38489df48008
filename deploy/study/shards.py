"""One study across machines: shards of its seeds (``semfleet study --shard I/N``) and their
merge (``semfleet study merge DIR... --out DIR``) into the archive a single run would write.

Shard I of N runs the study's seed indices i with i % N == I. Its results folder is a normal
one for its own seeds, plus a ``shard`` entry in results.json (docs/results.md) saying which
shard of which study it is; ``key`` fingerprints everything that decides the numbers besides
the seeds (the scenario's content, the methods, the belief configuration, the communication and
semfleet's version). The merge reads every shard's runs back (``deploy.study.archive.study_runs``)
and hands them, in seed order, to the very function that made the single run's archive, so the
two are the same but for the wall-clock figures.
"""

from __future__ import annotations

import dataclasses
import hashlib
import importlib.metadata
import shutil
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from deploy.base.errors import UsageError
from deploy.study.archive import ENVELOPE, ResultsArchive, read_folder, study_archive, study_runs
from deploy.study.paper_figures import PaperValue
from deploy.study.types import ASSOCIATE_ON, RunResult
from estimator.hybrid import BeliefConfig
from sim.scenario import Scenario
from sim.sensors import Detector

SHARD = "shard"  # the results.json key of a shard's entry
# The keys of a shard's entry that every shard of one study shares (all but ``index``).
SHARED = ("count", "seed", "runs", "snapshot_step", "snapshot_robot", "key")


@dataclass(frozen=True, slots=True)
class Shard:
    """Shard ``index`` of ``count``: the seed indices i with i % count == index."""

    index: int
    count: int

    def __post_init__(self) -> None:
        if not 0 <= self.index < self.count:
            raise ValueError(f"shard {self.index}/{self.count}: need 0 <= I < N")

    @classmethod
    def parse(cls, text: str) -> Shard:
        """``I/N`` → Shard(I, N); a ValueError says what is wrong."""
        index, slash, count = text.partition("/")
        if not (slash and index.strip().isdigit() and count.strip().isdigit()):
            raise ValueError(f"{text!r}: expected I/N, e.g. 0/4 (shard I of N, from 0)")
        return cls(int(index), int(count))

    def __str__(self) -> str:
        return f"{self.index}/{self.count}"

    def seeds(self, seeds: Sequence[int]) -> list[int]:
        """This shard's seeds of the study's ``seeds``."""
        return [s for i, s in enumerate(seeds) if i % self.count == self.index]


def study_key(
    scenario: Scenario,
    methods: Sequence[str],
    config: BeliefConfig,
    comm: str | None,
    gossip: str = "delta",
    detector: Detector | None = None,
    class_evidence: bool = True,
    associate_on: str = ASSOCIATE_ON[0],
) -> str:
    """The fingerprint of what decides a study's numbers besides its seeds (hex SHA-256). The
    scenario's ``source`` (the path it was read from) is left out: the same world may live in
    different folders on different machines. A ``detector`` of given-id frames (the default)
    leaves the key as it was before detectors existed, and so do ``class_evidence`` on and
    ``associate_on`` at its default."""
    try:
        version = importlib.metadata.version("semfleet")
    except importlib.metadata.PackageNotFoundError:
        version = "unknown"
    world = dataclasses.replace(scenario, source="")
    parts: tuple[object, ...] = (world, tuple(methods), config, comm, gossip, version)
    if detector is not None and not detector.exact:
        parts = (*parts, detector)
    if not class_evidence:
        parts = (*parts, "association on geometry alone")
    if associate_on != ASSOCIATE_ON[0]:
        parts = (*parts, f"association on {associate_on}")
    text = repr(parts)
    return hashlib.sha256(text.encode()).hexdigest()


def shard_entry(
    shard: Shard, seeds: Sequence[int], snapshot_step: int, snapshot_robot: str, key: str
) -> dict[str, Any]:
    """The ``shard`` entry of a shard's results.json; ``seeds``: the whole study's."""
    return {
        "index": shard.index,
        "count": shard.count,
        "seed": seeds[0],
        "runs": len(seeds),
        "snapshot_step": snapshot_step,
        "snapshot_robot": snapshot_robot,
        "key": key,
    }


@dataclass(frozen=True, slots=True)
class Merged:
    """The merged archive, its runs (seed order, no snapshots), the hypothesis plots' step and
    robot, and the folder of the shard that ran the study's first seed (it drew the hypothesis
    plots a single run draws)."""

    archive: ResultsArchive
    runs: list[RunResult]
    snapshot_step: int
    snapshot_robot: str
    first: Path


def merge_shards(folders: Sequence[Path]) -> Merged:
    """Every shard of one study, each exactly once, merged into the single run's archive; a
    usage error in one line for anything else (not a shard, another study or other settings,
    a shard twice, a shard missing)."""
    docs = {}
    for folder in folders:
        doc, arrays = read_folder(folder)
        if doc["study"] != "hybrid" or SHARD not in doc:
            raise UsageError(
                f"{folder}: not a shard of a study (made by semfleet study --shard I/N)"
            )
        docs[folder] = (doc, arrays)
    first, (ref, _) = next(iter(docs.items()))
    for folder, (doc, _) in docs.items():
        clash = _difference(ref, doc)
        if clash:
            raise UsageError(f"{folder} and {first} are shards of different studies: {clash}")
    entry = ref[SHARD]
    study_seeds = list(range(entry["seed"], entry["seed"] + entry["runs"]))
    by_index: dict[int, Path] = {}
    for folder, (doc, _) in docs.items():
        try:
            shard = Shard(int(doc[SHARD]["index"]), entry["count"])
        except (TypeError, ValueError) as exc:
            raise UsageError(f"{folder}: a broken shard entry ({exc})") from None
        if doc["seeds"] != shard.seeds(study_seeds):
            raise UsageError(f"{folder}: its seeds {doc['seeds']} are not those of shard {shard}")
        if shard.index in by_index:
            raise UsageError(
                f"{folder} and {by_index[shard.index]} are both shard {shard} "
                f"(seeds {_listed(doc['seeds'])})"
            )
        by_index[shard.index] = folder
    missing = [Shard(i, entry["count"]) for i in range(entry["count"]) if i not in by_index]
    missing = [s for s in missing if s.seeds(study_seeds)]
    if missing:
        seeds = sorted(x for s in missing for x in s.seeds(study_seeds))
        raise UsageError(
            f"shard {', '.join(map(str, missing))} missing: no folder given holds "
            f"seed{'s' if len(seeds) > 1 else ''} {_listed(seeds)}"
        )
    runs = {r.seed: r for folder, (doc, arrays) in docs.items() for r in _runs(folder, doc, arrays)}
    ordered = [runs[s] for s in study_seeds]
    skip = {*ENVELOPE, "robots", SHARD}
    settings = {k: v for k, v in ref.items() if k not in skip}
    archive = study_archive(ref["scenario"], ordered, list(ref["methods"]), settings)
    return Merged(archive, ordered, entry["snapshot_step"], entry["snapshot_robot"], by_index[0])


def _runs(folder: Path, doc: dict[str, Any], arrays: dict[str, Any]) -> list[RunResult]:
    """The runs of one shard; an array the shard's results.npz lacks or holds in the wrong shape
    is a ``UsageError`` naming the folder and the array."""
    try:
        return study_runs(doc, arrays)
    except KeyError as exc:
        raise UsageError(f"{folder}/results.npz: no array {exc}") from None
    except (ValueError, IndexError, TypeError) as exc:
        raise UsageError(f"{folder}/results.npz: {exc}") from None


def _difference(a: dict[str, Any], b: dict[str, Any]) -> str:
    """The first thing that tells the studies of results.json ``a`` and ``b`` apart, or ''."""
    pairs: list[tuple[str, Any, Any]] = [
        ("study", a["study"], b["study"]),
        ("scenario", a["scenario"], b["scenario"]),
        ("steps", a["steps"], b["steps"]),
        ("methods", list(a["methods"]), list(b["methods"])),
        ("robots", a.get("robots"), b.get("robots")),
    ]
    skip = {*ENVELOPE, "robots", SHARD}
    for key in [*(k for k in a if k not in skip), *(k for k in b if k not in skip and k not in a)]:
        pairs.append((key, a.get(key), b.get(key)))
    for key in SHARED:
        pairs.append((f"shard {key}", a[SHARD].get(key), b[SHARD].get(key)))
    for name, x, y in pairs:
        if x != y:
            if name == "shard key":
                return (
                    "the scenario, the belief configuration or semfleet's version differ "
                    f"(shard key {str(y)[:12]}… vs {str(x)[:12]}…)"
                )
            return f"{name} {y!r} vs {x!r}"
    return ""


def _listed(seeds: Sequence[int], most: int = 8) -> str:
    shown = ", ".join(map(str, seeds[:most]))
    return shown + (f", … ({len(seeds)} in all)" if len(seeds) > most else "")


def write_merged_plots(out: Path, merged: Merged, paper: Sequence[PaperValue] = ()) -> list[Path]:
    """The plots of ``deploy.study.plots.write_study_plots`` for the merged archive: the curves and
    the reliability diagram drawn from every run, and the hypothesis plots of the study's first
    seed copied from the shard that ran it (a merge has the runs' numbers, not their beliefs)."""
    from deploy.study.plots import write_curves_and_reliability

    doc, step = merged.archive.document(), merged.snapshot_step
    written = write_curves_and_reliability(out, doc, merged.runs, step, paper)
    pattern = f"hypotheses_*_{merged.snapshot_robot}_k{step}.png"
    for png in sorted(merged.first.glob(pattern)):
        written.append(Path(shutil.copyfile(png, out / png.name)))
    return written
