"""The experiment runner: cells (unit × method × overrides), one folder each, resumable.

A cell's folder holds ``mesh.ply`` with its sidecar ``mesh.ply.json`` and ``result.json`` (the
metrics, the timings, the counts, the parameters); it is filled under a staged name and put in
place whole (:class:`~ultraboneudf.io.commit.Commit`), so a cell is finished exactly when its folder
exists, and a run killed at any moment leaves no unfinished one. A failed reconstruction is a
finished cell too (its ``result.json`` says why); ``retry_failed`` runs those again, replacing
their folders. ``results.csv`` and ``results.sqlite`` are rebuilt together from the ``result.json``
files after every cell, so they always list exactly the finished cells. The run folder holds the
record ``ultraboneudf.json`` that marks it as one (:mod:`ultraboneudf.io.outputs`).
"""

from __future__ import annotations

import hashlib
import itertools
import json
import sqlite3
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .._version import __version__
from ..errors import InputError
from ..io import Commit, save_json
from ..io.outputs import FOLDER_RECORD, read_record, record
from ..progress import QUIET, Progress
from .manifest import Unit

EXPERIMENTS: dict[str, dict[str, Any]] = {
    "E1": {"methods": ["poisson", "funsr", "carotidudf", "capudf", "ultraboneudf"]},
    "E3": {"methods": ["ultraboneudf"], "sweep": {"loss.lambda_gs": ["0", "0.001", "0.01", "0.1", "1.0"]}},
    "E4": {"methods": ["ultraboneudf"], "sweep": {"model.depth": [str(d) for d in range(2, 11)]}},
    "E5": {"methods": ["ultraboneudf"], "set": ["loss.kind=pull", "loss.lambda_gs=0"],
           "sweep": {"loss.lambda_eik": ["0", "0.1", "1", "10"], "loss.lambda_os": ["0", "0.1", "1", "10"]}},
    "E6": {"methods": ["ultraboneudf"], "sweep": {"data.noise_sigma_mm": ["0", "0.5", "1.0", "1.5", "2.0"]}},
    "E7": {"methods": ["vanilla_udf", "ultraboneudf_pull", "ultraboneudf"]},
}
"""The experiments of docs/ALGORITHMS.md §6.4 as grids (E2, Table 4, is a report of E1's runs)."""

COLUMNS = ("cell", "unit", "specimen", "method", "preset", "seed", "overrides", "status", "reason",
           "cd_mm", "hd95_mm", "d_rg_mean_mm", "d_gr_mean_mm", "area_ratio", "nonmanifold_edges",
           "input_far_fraction", "mesh_far_area_fraction", "preprocess_s", "train_s", "extract_s",
           "total_s", "parameters", "faces", "version", "config_hash", "gt")


@dataclass(frozen=True)
class Cell:
    """One reconstruction of one unit with one method and its overrides."""

    unit: Unit
    method: str
    preset: str
    seed: int
    overrides: tuple[str, ...] = field(default_factory=tuple)

    @property
    def id(self) -> str:
        """A folder name that says what the cell is and cannot collide: unit, method, a short hash."""
        key = json.dumps([self.unit.id, self.method, self.preset, self.seed, list(self.overrides)])
        return f"{self.unit.id}__{self.method}__{hashlib.sha1(key.encode()).hexdigest()[:10]}"


def plan(units: list[Unit], experiment: str | None, methods: list[str], sweeps: list[str],
         sets: list[str], preset: str, seed: int) -> list[Cell]:
    """The cells of an experiment (``E1`` … ``E7``) or of a grid (``methods`` × every combination of
    the ``--sweep key=v1,v2`` values), each with the fixed ``sets``, over every unit."""
    grid: dict[str, list[str]] = {}
    fixed = list(sets)
    if experiment is not None:
        if experiment not in EXPERIMENTS:
            raise InputError(f"unknown experiment {experiment!r}; choose one of {', '.join(EXPERIMENTS)} "
                             f"or give --method/--sweep")
        spec = EXPERIMENTS[experiment]
        methods = methods or spec["methods"]
        grid.update(spec.get("sweep", {}))
        fixed = spec.get("set", []) + fixed
    for item in sweeps:
        key, _, values = item.partition("=")
        if not key or not values:
            raise InputError(f"--sweep expects key=v1,v2,…, got {item!r}")
        grid[key.strip()] = [v.strip() for v in values.split(",")]
    if not methods:
        raise InputError("no method: give an experiment (E1 … E7) or --method")
    combos = [tuple(f"{k}={v}" for k, v in zip(grid, values)) for values in itertools.product(*grid.values())]
    return [Cell(u, m, preset, seed, tuple(fixed) + combo) for u in units for m in methods for combo in combos]


ENGINES = ("local", "ray")


def run_cells(cells: list[Cell], out: Path, *, device: str = "auto", samples: int = 300_000,
              retry_failed: bool = False, workers: int = 1, progress: Progress = QUIET,
              engine: str = "local", address: str | None = None) -> dict[str, int]:
    """Run every unfinished cell into ``out/cells/<id>/``; returns the counts ``done`` (this run),
    ``skipped`` (finished before), ``failed`` (this run). Configurations are checked for every cell
    before the first one runs (a bad ``--set`` stops the run at once). ``workers > 1`` runs that
    many cells at once in a pool of processes on this machine, the CPU threads shared among them.
    ``engine="ray"`` sends the cells to a Ray cluster instead (``address``; a local one when
    ``None``), one CPU each, or one GPU each when ``device`` is CUDA; a cell whose worker dies is
    retried (it starts again from an empty folder). The folders and tables are the same; ``out``
    must then be on storage that every node of the cluster sees."""
    from ..pipeline import configure

    if engine not in ENGINES:
        raise InputError(f"unknown engine {engine!r}; choose one of {', '.join(ENGINES)}")
    configs = {}  # each cell's configuration, resolved once, before the first cell runs
    for cell in cells:
        configs[cell.id] = configure(cell.preset, cell.method, assignments=list(cell.overrides))
        if not (out / "cells" / cell.id).resolve().is_relative_to((out / "cells").resolve()):
            raise InputError(f"cell {cell.id!r}: its folder would lie outside {out / 'cells'}")
    out.mkdir(parents=True, exist_ok=True)
    if read_record(out / FOLDER_RECORD) is None:
        save_json(record("bench run"), out / FOLDER_RECORD)
    counts = {"done": 0, "skipped": 0, "failed": 0}
    todo = []
    for cell in cells:
        result = out / "cells" / cell.id / "result.json"
        if result.exists() and not (retry_failed and json.loads(result.read_text()).get("status") == "failed"):
            counts["skipped"] += 1
        else:
            todo.append(cell)
    progress.log(f"bench: {len(cells)} cells, {counts['skipped']} finished before, {len(todo)} to run")
    with progress.stage("cells", len(todo)) as advance:
        def finished(row: dict[str, Any]) -> None:
            counts["failed" if row["status"] == "failed" else "done"] += 1
            write_tables(out)
            advance()

        if engine == "ray":
            _run_on_ray(todo, configs, out, device, samples, address, finished)
        elif workers <= 1:
            for cell in todo:
                finished(_run_cell(cell, configs[cell.id], out / "cells" / cell.id, device, samples))
        else:
            import multiprocessing
            import os
            from concurrent.futures import ProcessPoolExecutor, as_completed

            threads = max(1, (os.cpu_count() or 1) // workers)
            with ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("spawn"),
                                     initializer=_worker_init, initargs=(threads,)) as pool:
                futures = [pool.submit(_run_cell, c, configs[c.id], out / "cells" / c.id, device, samples)
                           for c in todo]
                for future in as_completed(futures):
                    finished(future.result())
    write_tables(out)
    return counts


RAY_RETRIES = 3
"""Times a cell is started again when its Ray worker dies (killed, out of memory, a lost node)."""


def _run_on_ray(cells: list[Cell], configs: dict[str, Any], out: Path, device: str, samples: int,
                address: str | None, finished: Any) -> None:
    """The cells as Ray tasks; ``finished(row)`` as each returns, in the order they finish."""
    try:
        import ray
    except ImportError:
        raise InputError("the Ray engine needs Ray: pip install 'ultraboneudf[ray]'") from None
    started = not ray.is_initialized()
    if started:
        try:
            ray.init(address=address, include_dashboard=False, log_to_driver=False)
        except (ConnectionError, ValueError, RuntimeError) as exc:
            raise InputError(f"cannot reach the Ray cluster at {address or 'a new local instance'}: "
                             f"{exc}") from None
    try:
        gpu = str(device).startswith("cuda")
        task = ray.remote(num_cpus=1, num_gpus=1 if gpu else 0, max_retries=RAY_RETRIES)(_run_cell)
        pending = [task.remote(c, configs[c.id], out / "cells" / c.id, device, samples) for c in cells]
        while pending:
            ready, pending = ray.wait(pending, num_returns=1)
            finished(ray.get(ready[0]))
    finally:
        if started:
            ray.shutdown()


def _worker_init(threads: int) -> None:
    import torch

    torch.set_num_threads(threads)


def _run_cell(cell: Cell, config: Any, target: Path, device: str, samples: int) -> dict[str, Any]:
    """Run one cell with its resolved ``config`` into a staged folder and put it in place of
    ``target`` whole."""
    with Commit() as commit:
        row = _fill_cell(cell, config, commit.folder(target), device, samples)
        commit.commit()
    return row


def _fill_cell(cell: Cell, config: Any, folder: Path, device: str, samples: int) -> dict[str, Any]:
    import ultraboneudf
    from ..evaluation import evaluate

    row: dict[str, Any] = {"cell": cell.id, "unit": cell.unit.id, "specimen": cell.unit.specimen,
                           "method": cell.method, "preset": cell.preset, "seed": cell.seed,
                           "overrides": " ".join(cell.overrides), "version": __version__,
                           "gt": str(cell.unit.gt)}
    try:
        points, probe, frames = _read_input(cell.unit.input)
        rec = ultraboneudf.reconstruct(points, preset=cell.preset, device=device, seed=cell.seed,
                                       method=cell.method, config=config, source=str(cell.unit.input),
                                       probe_positions=probe, frame_index=frames,
                                       warn=False)  # the data-fit figures are in the row
        resolved = json.dumps(rec.config.to_dict(), sort_keys=True).encode()
        row["config_hash"] = hashlib.sha256(resolved).hexdigest()[:16]
        row.update({k: rec.timings.get(k) for k in ("preprocess_s", "train_s", "extract_s", "total_s")})
        row.update(parameters=rec.counts.get("parameters"), faces=rec.counts.get("faces"),
                   input_far_fraction=rec.data_fit.get("input_far_fraction"),
                   mesh_far_area_fraction=rec.data_fit.get("mesh_far_area_fraction"),
                   nonmanifold_edges=rec.quality.get("nonmanifold_edges"))
        if rec.mesh is None:
            row.update(status="failed", reason="no surface found")
        else:
            rec.save(folder / "mesh.ply")
            truth = ultraboneudf.load_mesh(cell.unit.gt)
            raw = points if cell.unit.pseudo_gt_mm is not None else None
            ev = evaluate(rec.mesh, truth, raw_points=raw, pseudo_gt_mm=cell.unit.pseudo_gt_mm,
                          samples=samples, seed=0, gt_source=str(cell.unit.gt))
            row.update({k: getattr(ev, k) for k in ("cd_mm", "hd95_mm", "d_rg_mean_mm", "d_gr_mean_mm")})
            row["area_ratio"] = float(rec.mesh.area / truth.area)
            row.update(status="failed" if ev.failed else "ok", reason=ev.reason)
    except InputError as exc:
        row.update(status="failed", reason=str(exc))
    save_json({k: row.get(k) for k in COLUMNS}, folder / "result.json")
    return row


def _read_input(path: Path) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
    """Points (mm) and, from an ``.npz`` that has them, a cloud ``sweep2points`` wrote or a sweep, the
    probe positions and frame indices (a sweep's frames registered to each other, as ``reconstruct
    SWEEP`` does)."""
    from ..io import load_points, load_sweep_columns

    if path.suffix.lower() == ".npz":
        with np.load(path) as data:
            if "probe" in data.files and "points" in data.files:
                frames = np.asarray(data["frame"]) if "frame" in data.files else None
                return load_points(path), np.asarray(data["probe"], dtype=np.float64), frames
    if path.is_dir() or path.suffix.lower() in (".mha", ".mhd", ".nrrd"):
        from ..sweep.front_end import sweep_points

        sp = sweep_points(path)
        return sp.points, sp.probe_position, sp.frame_index
    points = load_points(path)
    return (points, *load_sweep_columns(path, len(points)))


def earlier_run(out: Path) -> bool:
    """``out`` is the folder of an earlier run: it holds the record of one, or (an earlier version's
    run) nothing but ``cells/`` and the two tables."""
    if not out.is_dir() or out.is_symlink():
        return False
    if read_record(out / FOLDER_RECORD) is not None:
        return True
    names = {p.name for p in out.iterdir()}
    return "cells" in names and names <= {"cells", "results.csv", "results.sqlite"}


def finished_rows(out: Path) -> list[dict[str, Any]]:
    """The ``result.json`` rows of every finished cell under ``out``, sorted by cell id."""
    return [json.loads(p.read_text()) for p in sorted((out / "cells").glob("*/result.json"))
            if not p.parent.name.startswith(".")]  # not a cell being written or replaced


def write_tables(out: Path) -> None:
    """``results.csv`` and ``results.sqlite`` (table ``cells``) from the finished cells, put in
    place together."""
    import csv
    import io

    rows = finished_rows(out)
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=COLUMNS, lineterminator="\n")
    w.writeheader()
    w.writerows(rows)
    with Commit() as commit:
        commit.write(out / "results.csv", buf.getvalue().encode("utf-8"))
        db = sqlite3.connect(commit.file(out / "results.sqlite"))
        try:
            with db:
                db.execute(f"CREATE TABLE cells ({', '.join(COLUMNS)})")
                db.executemany(f"INSERT INTO cells VALUES ({', '.join('?' * len(COLUMNS))})",
                               [[r.get(c) for c in COLUMNS] for r in rows])
        finally:
            db.close()
        commit.commit()
