"""Committed reproduce-profile results, shown in the stored notebooks beside the live CI-profile run.

A notebook's CI profile must run in a minute, so its live numbers come from one seed and a small
budget. Its takeaways rest on the **reproduce profile** (≥ 5 seeds, full budget): when the notebook
runs with ``PROFILE = "reproduce"`` (``make reproduce``) it calls :func:`save`, which writes
``notebooks/results/<name>.json`` stamped with the git commit, date, library versions and the
notebook's experiment config; in every profile it then calls :func:`load` with the config its code
has *now*, and shows the committed table. :func:`load` refuses a file whose config differs from the
notebook's (a changed epoch count, lr, seed list, …), a file computed with other
course-backbone weights (compared by :func:`backbone_fingerprint`), and a file computed on another
synthetic world (compared by :func:`world_fingerprints`), so nbval fails and a result can never go
stale silently: re-run ``make reproduce`` (or that notebook with ``PROFILE = "reproduce"``) and commit.
Verdicts on these numbers follow the course's one rule, :mod:`vpr_nb.verdict`.

**Keys.** A results file is keyed on three things, each checked by :func:`load`:

* ``config``: the notebook's experiment settings, as the notebook passes them;
* ``course_backbone``: the sha256 of the course backbone's tensors (``vpr_nb/weights/course_backbone.pt``);
* ``worlds``: for every synthetic world the experiment config names, the world's fingerprint
  (:meth:`vpr_nb.synthetic.WorldConfig.fingerprint`: every field of its ``WorldConfig`` and the
  condition rows it uses) and its fields. The notebooks need no code for this: the world is found in
  the config they already pass, under ``"world"`` (a dict with ``preset``, optional ``size``
  and ``overrides``, as given to ``make_dataset``) or ``"worlds"`` (a dict of such dicts), so a
  changed ``WorldConfig`` default, a kind's changed deviation or a changed condition row makes the
  file stale, and the error names the fields that changed. Rendering constants are not scene knobs
  and are not in the fingerprint; they are pinned by the pixel hashes of ``tests/test_synthetic.py``,
  whose failure says to re-run the reproduce profile.
"""
from __future__ import annotations

import datetime as _dt
import hashlib
import json
import math
import os
import time
from collections.abc import Mapping
from pathlib import Path

import torch

from .engine import PROCESS_TOKEN, TIMES_ENV
from .package_data import committed_results_dir, results_dir_for_writing
from .report import jsonable, environment_header, uncommitted_changes
from .reproduce_one import run_seconds
from .schedule import parse_round
from .models import read_weights
from .pretrain import CHECKPOINT
from .synthetic import make_config
from .synthetic.config import OPTIONAL_CONTENT, WorldConfig


ALLOW_DIRTY_ENV = "VPR_NB_ALLOW_DIRTY"   # =1: a trial reproduce run may save from a dirty tree
_TASKS_COUNTED: dict[str, int] = {}      # a task-times file -> its bytes already counted by a save here


def tasks_since_last_save(environ=None) -> dict | None:
    """The fine-tunes this process logged (``$VPR_NB_TASK_TIMES``, :func:`vpr_nb.engine.log_round`) since its
    last :func:`save`: ``{"run": n, "reused": m, "task seconds": s}``, where a task reused from the task store
    counts the time it took when it ran; None when nothing is logged. A results file made by a run that was
    interrupted and started again records a short ``seconds`` (only what was left to do) and its whole cost
    here. Rounds another process logged (an earlier attempt's, in the same file) are not counted: the tasks
    they ran count once, as reused ones, in this process's rounds."""
    path = (os.environ if environ is None else environ).get(TIMES_ENV, "").strip()
    if not path or not os.path.isfile(path):
        return None
    data = Path(path).read_bytes()
    start = _TASKS_COUNTED.get(path, 0)
    start = start if start <= len(data) else 0          # the file was started again
    end = data.rfind(b"\n") + 1                          # whole lines only
    _TASKS_COUNTED[path] = max(end, start)
    rounds = [r for r in map(parse_round, data[start:end].splitlines())   # torn lines skipped, and the rounds of
              if r is not None and r.get("process", PROCESS_TOKEN) == PROCESS_TOKEN]   # another process
    seconds = [x for r in rounds for x in r["seconds"]]
    reused = [x for r in rounds for x in r["reused"]]
    if not seconds:
        return None
    return {"run": len(seconds), "reused": sum(reused), "task seconds": round(sum(seconds), 1)}


def run_minutes(doc) -> float:
    """What a loaded results document's experiment took on the 2 cores, in minutes, counting fine-tunes reused
    from an earlier attempt at the time each took (:func:`vpr_nb.reproduce_one.run_seconds`); ValueError when
    it records no time."""
    seconds = run_seconds(doc)
    if seconds is None:
        raise ValueError("these results record no run time (their 'seconds'); make them again with the notebook's "
                         "reproduce profile")
    return seconds / 60


def _canonical(value):
    """``value`` as JSON would give it back (tuples → lists, numpy scalars → numbers, keys → str)."""
    return json.loads(json.dumps(jsonable(value)))


def backbone_fingerprint(path=None) -> str:
    """sha256 of the course backbone's *tensors* (names, dtypes, shapes, values), not of the file's bytes,
    so results are tied to the weights they were computed with."""

    state = read_weights(Path(path) if path is not None else CHECKPOINT, "course backbone")
    h = hashlib.sha256()
    for k in sorted(state):
        t = state[k].contiguous()
        h.update(f"{k}|{t.dtype}|{tuple(t.shape)}|".encode())
        h.update(t.view(torch.uint8).numpy().tobytes() if t.numel() else b"")
    return h.hexdigest()


def world_fingerprints(config: Mapping) -> dict[str, dict]:
    """{key: {"fingerprint", "world", "config"}} of the synthetic worlds ``config`` names: ``config["world"]``
    (key ``"world"``) and each ``config["worlds"][name]`` (key ``"worlds.<name>"``), every one a dict with
    ``preset``, optional ``size`` and ``overrides`` (other entries, such as the seed, are the
    experiment's and stay in ``config``). Unknown presets or options raise ValueError."""

    specs = {}
    if isinstance(config.get("world"), Mapping):
        specs["world"] = config["world"]
    worlds = config.get("worlds") or {}
    if not isinstance(worlds, Mapping):
        raise ValueError(f"config['worlds'] must be a dict {{name: world}}, got {type(worlds).__name__}")
    for name, spec in worlds.items():
        specs[f"worlds.{name}"] = spec
    out = {}
    for key, spec in specs.items():
        if not isinstance(spec, Mapping) or not isinstance(spec.get("preset"), str):
            raise ValueError(f"config[{key!r}] must be a dict with a 'preset' (and optional 'size', 'overrides'), "
                             f"got {spec!r}")
        cfg = make_config(spec["preset"], spec.get("size", "tiny"), **dict(spec.get("overrides") or {}))
        out[key] = {"fingerprint": cfg.fingerprint(), "world": f"{cfg.preset}-{cfg.size}",
                    "config": _canonical(cfg.scene_fields())}
    return out


def _stale_worlds(path: Path, committed, now: dict) -> str | None:
    """Why the committed world records differ from today's (None when they do not)."""
    committed = committed if isinstance(committed, Mapping) else {}
    for key, rec in now.items():
        old = committed.get(key)
        if not isinstance(old, Mapping) or "fingerprint" not in old:
            return (f"notebooks/results/{path.name} is stale: it holds no fingerprint of the synthetic world "
                    f"config[{key!r}] ({rec['world']}), so it cannot be shown to match today's world")
        if old["fingerprint"] == rec["fingerprint"]:
            continue
        was, cur = old.get("config") or {}, rec["config"]
        off = {k: _canonical(getattr(WorldConfig, k)) for k in OPTIONAL_CONTENT}     # absent = at its default
        fields = sorted(k for k in set(was) | set(cur) if was.get(k, off.get(k, "(absent)")) != cur.get(k, off.get(k, "(absent)")))
        what = (f"in WorldConfig field(s) {fields} (committed {[was.get(k, '(absent)') for k in fields]}, now "
                f"{[cur.get(k, '(absent)') for k in fields]})" if fields else
                "in the condition rows it uses (vpr_nb.synthetic.CONDITIONS)")
        return (f"notebooks/results/{path.name} is stale: it was computed on another synthetic world: "
                f"config[{key!r}] ({rec['world']}) differs from today's {what}")
    extra = sorted(set(committed) - set(now))
    if extra:
        return (f"notebooks/results/{path.name} is stale: it was computed on worlds {extra} that the notebook's "
                f"config no longer names")
    return None


def results_path(name: str, results_dir, *, write: bool = False) -> Path:
    if not isinstance(name, str) or not name or "/" in name:
        raise ValueError(f"name must be a notebook stem such as '03_distance_ranking_weighted_loss', got {name!r}")
    if results_dir is None:     # notebooks/results/ of the clone, or the copy installed with vpr_nb (package_data)
        results_dir = results_dir_for_writing() if write else committed_results_dir()
    return Path(results_dir) / f"{name}.json"


def save(name: str, config: Mapping, results: Mapping, *, results_dir=None) -> Path:
    """Write ``results`` (numbers, strings, lists, dicts) for notebook ``name`` with its ``config``
    and a stamp (git commit, date, versions, and the fine-tunes logged since the last save,
    :func:`tasks_since_last_save`), atomically. Returns the path.

    Refuses (``ValueError`` naming the key path) results that :func:`load` would refuse: a NaN / inf, or a
    number outside its metric's range (a recall above 1, a negative count, …)."""

    if not isinstance(config, Mapping) or not isinstance(results, Mapping):
        raise ValueError("config and results must be dicts (the experiment's settings and its tables)")
    path = results_path(name, results_dir, write=True)
    problem = _number_problem({"results": _canonical(results)})
    if problem:          # load would refuse the file: do not write it
        raise ValueError(f"refusing to write {path.name}: {problem}; fix that run (a diverged seed, a wrong "
                         f"metric?) and re-run the notebook with PROFILE = 'reproduce'")
    stamp = environment_header("reproduce")
    committed_dir = results_dir is None            # the repository's notebooks/results/: what gets committed
    if committed_dir and stamp["git commit"].endswith("(with uncommitted changes)") \
            and os.environ.get(ALLOW_DIRTY_ENV) != "1":
        raise ValueError(f"refusing to write notebooks/results/{path.name} from a working tree with uncommitted "
                         f"changes ({', '.join(uncommitted_changes()[:5])}): committed results must come from "
                         f"a clean commit. Commit (or stash) first; for a trial run set {ALLOW_DIRTY_ENV}=1 "
                         f"(the file is then stamped 'with uncommitted changes' and must not be committed)")
    stamp["date"] = _dt.datetime.now(_dt.timezone.utc).strftime("%Y-%m-%d")
    tasks = tasks_since_last_save()
    if tasks is not None:
        stamp["fine-tunes"] = tasks
    doc = {"notebook": name, "stamp": stamp, "course_backbone": backbone_fingerprint(),
           "worlds": world_fingerprints(config), "config": _canonical(config), "results": _canonical(results)}
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".json.tmp")
    tmp.write_text(json.dumps(doc, indent=1, sort_keys=False) + "\n", encoding="utf-8")
    tmp.replace(path)
    return path


def _json_kind(value) -> str:
    return {dict: "object", list: "array", str: "string", bool: "boolean", int: "number", float: "number"}.get(
        type(value), "null")


class _NonStandardNumber(str):
    """A ``NaN`` / ``Infinity`` / ``-Infinity`` token, which Python's json accepts and strict JSON does not:
    kept as a marker by :func:`_read_doc` so that :func:`_number_problem` can name its key path."""


# The range of a number in ``results``, from the key names the notebooks write (notebooks/results/*.json): the
# innermost key on the path that names a metric decides (``rows.T-Loss.R@1[2]`` → R@1; ``best epoch.<method>[0]``
# → best epoch; ``val R@1 per lr.<method>.0.001[1]`` → R@1). A key naming a difference (gain, gap, delta, …)
# and every other key only has to be finite.
_EPS = 1e-6                                        # float32 round-off of a cosine or a mean of shares
_RELATIVE_WORDS = ("gain", "gap", "diff", "delta", "change", "improvement", "−", " - ", " vs ")
_RULES = (
    ("a recall, probability or share, in [0, 1]", lambda x: -_EPS <= x <= 1 + _EPS,
     lambda k: k.startswith("p(") or any(w in k for w in ("r@", "recall", "share", "pairs in order",
                                                          "entropy / log m", "near duplicates"))),
    ("a cosine or rank correlation, in [-1, 1]", lambda x: -1 - _EPS <= x <= 1 + _EPS,
     lambda k: "cosine" in k or "kendall tau" in k),
    ("a count, a whole number >= 0", lambda x: x >= 0 and float(x).is_integer(),
     lambda k: k in ("best epoch", "epochs run", "steps", "dim", "bytes", "keys")),
    ("a duration in seconds, >= 0", lambda x: x >= 0, lambda k: k == "seconds"),
    ("a learning rate, > 0", lambda x: x > 0, lambda k: k == "lr"),
)


def _rule_for(keys: tuple):
    """The (description, check) of the innermost key of ``keys`` that names a metric; None: finite is enough."""
    for key in reversed([k.lower() for k in keys if isinstance(k, str)]):
        if any(w in key for w in _RELATIVE_WORDS):
            return None
        for what, ok, names in _RULES:
            if names(key):
                return what, ok
    return None


def _key_path(keys: tuple) -> str:
    """``results.rows.T-Loss.R@1[2]``; a key holding a dot or bracket is quoted (``"p(0,10 m) Eq.3"``)."""
    out = ""
    for k in keys:
        if isinstance(k, int):
            out += f"[{k}]"
        else:
            out += ("." if out else "") + (json.dumps(k, ensure_ascii=False) if any(c in k for c in ".[]\"") else k)
    return out


def _number_problem(value, keys: tuple = ()) -> str | None:
    """What is wrong with the first bad number in ``value`` (``"results.rows.T.R@1[2] is NaN ..."``), or None.

    Everywhere: a ``NaN`` / ``Infinity`` token or a non-finite float (``1e999``). Under ``results`` also the
    strings ``"nan"`` / ``"inf"`` / ``"-inf"`` (how :func:`vpr_nb.report.jsonable` writes a non-finite float) and a
    number outside its metric's range (:data:`_RULES`)."""
    if isinstance(value, Mapping):
        for k, v in value.items():
            problem = _number_problem(v, keys + (str(k),))
            if problem:
                return problem
        return None
    if isinstance(value, list):
        for i, v in enumerate(value):
            problem = _number_problem(v, keys + (i,))
            if problem:
                return problem
        return None
    where, in_results = _key_path(keys) or "its only value", bool(keys) and keys[0] == "results"
    if isinstance(value, _NonStandardNumber):
        return f"{where} is {value} (a JSON token that strict JSON does not allow: a diverged or failed run?)"
    if in_results and isinstance(value, str) and value.strip().lower() in ("nan", "inf", "-inf", "+inf"):
        return f"{where} is {value!r} (a NaN or inf, which JSON can only hold as text: a diverged or failed run?)"
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return None
    if isinstance(value, float) and not math.isfinite(value):
        return (f"{where} is {'NaN' if math.isnan(value) else value} (a number too large for a float, such as "
                f"1e999, is read as inf)")
    rule = _rule_for(keys[1:]) if in_results else None
    if rule and not rule[1](value):
        return f"{where} is {value!r}, but it must be {rule[0]} (by its key's name)"
    return None


def _read_doc(path: Path) -> dict:
    """The JSON object of a results file, with the keys :func:`save` writes; ValueError naming the file."""
    fix = (f"restore it with `git checkout -- notebooks/results/{path.name}` or re-run the notebook with "
           f"PROFILE = 'reproduce' and commit")
    try:
        doc = json.loads(path.read_text(encoding="utf-8"), parse_constant=_NonStandardNumber)
    except UnicodeDecodeError as exc:
        raise ValueError(f"{path} is not UTF-8 text (byte {exc.start}); {fix}") from None
    except json.JSONDecodeError as exc:
        raise ValueError(f"{path} is not valid JSON ({exc.msg} at line {exc.lineno}, column {exc.colno}; "
                         f"truncated?); {fix}") from None
    problem = _number_problem(doc)
    if problem:
        raise ValueError(f"{path}: {problem}; re-make it with `make reproduce` (or the notebook with PROFILE = "
                         f"'reproduce') and commit, or restore it with `git checkout -- notebooks/results/{path.name}`")
    if not isinstance(doc, dict):
        raise ValueError(f"{path} holds a JSON {_json_kind(doc)}, not a results object "
                         f"{{'config', 'results', ...}}; {fix}")
    for key, kind in (("config", dict), ("results", dict), ("course_backbone", str)):
        if key not in doc:
            raise ValueError(f"{path} has no {key!r} entry, so it is not a results file written by "
                             f"vpr_nb.results.save; {fix}")
        if not isinstance(doc[key], kind):
            raise ValueError(f"{path}: its {key!r} entry is a JSON {_json_kind(doc[key])}, not "
                             f"{'an object' if kind is dict else 'a string'}; {fix}")
    return doc


def made_or_loaded(name: str, config: Mapping, run, profile: str, *, results_dir=None) -> dict:
    """A notebook's package experiment: with ``profile == "reproduce"``, ``run()`` (no arguments) is timed and its
    results saved with their ``"seconds"`` (:func:`save`); in every profile the committed file is then
    returned by :func:`load` (so the reproduce profile shows what it saved, the CI profile what is committed)."""
    if not callable(run):
        raise ValueError(f"run must be a function of no arguments that returns the results, got {run!r}")
    if profile == "reproduce":
        t0 = time.perf_counter()
        out = run()
        save(name, config, {**out, "seconds": round(time.perf_counter() - t0, 1)}, results_dir=results_dir)
    return load(name, config, results_dir=results_dir)


def load(name: str, config: Mapping, *, results_dir=None) -> dict:
    """The committed results of notebook ``name``; ``config`` must equal the one they were made with,
    on today's course backbone and synthetic world(s) (the module docstring lists the keys).

    Raises ``FileNotFoundError`` when nothing is committed, ``ValueError`` naming the file when it is
    not a results file (not JSON, truncated, not an object, or without its ``config`` / ``results`` /
    ``course_backbone`` entries), ``ValueError`` naming the file and the key path of a number that is not
    finite (a ``NaN`` / ``Infinity`` token, ``1e999``, or the text ``"nan"``) or lies outside the range its
    key names (recalls, R@N, probabilities and shares in [0, 1]; cosines and Kendall tau in [-1, 1]; epochs,
    steps, dims, bytes and keys whole and >= 0; seconds >= 0; lr > 0; any other key: finite), and
    ``ValueError`` naming what differs when the notebook's experiment, the backbone or a world changed since
    (the results are stale).
    """
    path = results_path(name, results_dir)
    if not path.is_file():
        raise FileNotFoundError(f"no committed reproduce-profile results at notebooks/results/{path.name}; "
                                f"run the notebook with PROFILE = 'reproduce' (make reproduce) and commit the file")
    doc = _read_doc(path)
    want, have = _canonical(config), doc["config"]
    if want != have:
        keys = sorted(k for k in set(want) | set(have or {}) if (have or {}).get(k) != want.get(k))
        raise ValueError(f"notebooks/results/{path.name} is stale: its experiment config differs from the "
                         f"notebook's in {keys} (committed {[(have or {}).get(k) for k in keys]}, notebook "
                         f"{[want.get(k) for k in keys]}); re-run the notebook with PROFILE = 'reproduce' and commit")
    if doc.get("course_backbone") != backbone_fingerprint():
        raise ValueError(f"notebooks/results/{path.name} is stale: it was computed with other course-backbone "
                         f"weights than vpr_nb/weights/course_backbone.pt holds now; re-run the notebook with "
                         f"PROFILE = 'reproduce' and commit")
    why = _stale_worlds(path, doc.get("worlds"), world_fingerprints(config))
    if why:
        raise ValueError(f"{why}; re-run the notebook with PROFILE = 'reproduce' and commit")
    return doc


def _finite_values(values, what: str, labels=None) -> list[float]:
    """``values`` as floats; ValueError naming ``what`` and the entry (``labels[i]``, else its position)
    that is not a finite number."""
    try:
        values = list(values)
    except TypeError:
        raise ValueError(f"{what} must be a list of numbers (one per seed), got {values!r}") from None
    vals = []
    for i, v in enumerate(values):
        where = f"seed {labels[i]}" if labels is not None and i < len(labels) else f"entry {i}"
        try:
            x = float(v)
        except (TypeError, ValueError):
            raise ValueError(f"{what}, {where}: {v!r} is not a number") from None
        if not math.isfinite(x):
            raise ValueError(f"{what}, {where}: the value is {x}, not a finite number (a diverged or failed "
                             f"run?); re-run that seed or leave it out of every compared method")
        vals.append(x)
    return vals


def mean_std(values, what: str = "mean_std values") -> tuple[float, float]:
    """Mean and sample standard deviation (0 for a single value) of a list of finite numbers.

    A NaN / inf / non-number raises ValueError naming ``what`` and the entry."""
    vals = _finite_values(values, what)
    if not vals:
        raise ValueError(f"{what}: mean_std needs at least one value")
    m = sum(vals) / len(vals)
    sd = math.sqrt(sum((v - m) ** 2 for v in vals) / (len(vals) - 1)) if len(vals) > 1 else 0.0
    return m, sd


def print_table(rows: Mapping, title: str, label_width: int = 22, col_width: int = 24) -> None:
    """Print ``rows`` = {column name: {metric: formatted value}} as a text table, one metric per line
    (every column must have the metrics of the first)."""
    if not isinstance(rows, Mapping) or not rows:
        raise ValueError("rows must be a non-empty dict {column name: {metric: value}}")
    names = list(rows)
    metrics = list(rows[names[0]])
    missing = {n: sorted(set(metrics) - set(rows[n])) for n in names if set(metrics) - set(rows[n])}
    if missing:
        raise ValueError(f"every column needs the metrics of the first; missing: {missing}")
    print(title)
    print(f"{'':>{label_width}}" + "".join(f"{n:>{col_width}}" for n in names))
    for metric in metrics:
        print(f"{metric:>{label_width}}" + "".join(f"{rows[n][metric]:>{col_width}}" for n in names))
