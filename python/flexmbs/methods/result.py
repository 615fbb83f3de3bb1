"""Result and history objects shared by the weakly and the fully coupled methods.

`OptimizationResult` is what `optimize_weakly` / the fully coupled optimizer return;
`HistoryWriter` appends one JSON line per cycle (weakly) or iteration (fully) to a file as
the run goes, so that an interrupted run loses nothing already computed: each record is one
write of a whole line, flushed to disk (fsync) before the run goes on. A line cut short by a
crash or a full disk is the file's last one and has no newline; `read_history` skips it with
a warning instead of reading it back as a record.

History records are plain dicts. Keys used by both methods (others may be added):
    iteration        cycle / iteration number (the paper's "Iter."; fully coupled: 0 = start)
    design           design analysed in this cycle / iteration (list, the variables' units)
    objective        its objective value; mass_kg its mass (None when no mass is defined)
    max_violation    max g of that design in the full simulation (relative to the limits)
    active_steps     {constraint response: [1-based rows, i.e. time steps for every_step
                     constraints]} within active_tol of the limit (the paper's Table 8)
Weakly coupled: esl_change (eq. 25, None in the first cycle; esl_change_per_body),
inner_iterations and predicted_max_violation of the static problem that produced the design,
whose active steps are active_steps, simulation_active_steps (rows where the cycle's full
simulation is within active_tol of the limit), static_message (None when SLSQP succeeded).
Fully coupled: responses (largest value of each), objective_rel_change, design_rel_change,
kkt_residual, simulations, gradient_evaluations, wall_time_s; in the file only (not in
`records` nor in the result's history), evaluations: every analysis made since the previous
record (scaled design x, gradient flag, objective, d_objective, constraints, jacobian,
constraint_names as [[name, rows], ...], values: every response, histories in full), what a
resumed run replays.

Resume (`HistoryWriter(path, resume=True)`, the optimizers' ``resume=True``): the records in
the file are read back (`previous`), the records the resumed run makes again are checked
against them instead of being written twice, and the run appends the rest.

Fingerprint: the first record's line carries, in the file only, the fingerprint of what the
history answers (flexmbs.model.fingerprint: the case description as resolved, the method and its
options, the flexmbs version; `HistoryWriter.check_fingerprint`) and the run's options whole
(key ``options``: flexmbs.model.options, as plain data); a resume whose fingerprint
differs, or from a file without one, is refused (ModelError naming what differs).
"""
from __future__ import annotations

import json
import os
import warnings
from dataclasses import dataclass, field

import numpy as np

from flexmbs.analysis.accuracy import describe_verification
from flexmbs.errors import ModelError
from flexmbs.files import check_regular_file, jsonable, save_figure
from flexmbs.model.fingerprint import differences
from flexmbs.problem import FEASIBILITY_TOL, is_feasible

__all__ = ["OptimizationResult", "HistoryWriter", "read_history", "jsonable", "open_history"]


def _locked(path):
    """The file at `path` opened for reading and appending without truncating it (created
    when missing), with an exclusive advisory lock (fcntl.flock) held until it is closed;
    ModelError naming the file when another process holds it."""
    import fcntl
    fh = open(os.open(path, os.O_RDWR | os.O_CREAT, 0o666), "r+", encoding="utf-8")
    try:
        fcntl.flock(fh.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        fh.close()
        raise ModelError(f"history {os.fspath(path)!r} is being written by another run (it is "
                         "locked): wait for that run to end, or give another history "
                         "file") from None
    return fh


def _whole_lines(fh):
    """Keep only whole records at the end of a history opened by `_locked`: a last line cut
    short (no newline, not JSON: an interrupted write) is cut off; a last line that is a
    whole record without its newline gets one."""
    fh.seek(0, os.SEEK_END)
    size = fh.tell()
    if not size:
        return
    raw = fh.buffer if hasattr(fh, "buffer") else fh
    raw.seek(0)
    data = raw.read()
    if data.endswith(b"\n"):
        return
    cut = data.rfind(b"\n") + 1
    try:
        json.loads(data[cut:])
    except ValueError:
        fh.truncate(cut)
        return
    raw.seek(0, os.SEEK_END)
    raw.write(b"\n")
    raw.flush()


class HistoryWriter:
    """Append one JSON object per line to a file, flushed at every record.

    Parameters
    ----------
    path : str or os.PathLike, or None
        None: records are only kept in memory (`records`).
    mode : {'w', 'a'}, default 'w'
        'w' starts a new file, 'a' appends to an existing one.
    resume : bool, default False
        Continue the history of an interrupted run: the file's records are read back
        (`previous`; a last line cut short is dropped from the file), and the first
        len(previous) records written are checked against them (same iteration and design,
        else ModelError: the resumed run does not follow the interrupted one) and kept in
        memory only, since the file holds them already; later ones are appended. A missing
        file starts a new history.

    Attributes
    ----------
    records : the records of this run (without the file-only parts, see `write`).
    previous : the records found in the file when resuming (else []).
    """

    def __init__(self, path=None, mode="w", resume=False):
        if mode not in ("w", "a"):
            raise ValueError(f"HistoryWriter mode must be 'w' or 'a', got {mode!r}")
        if path is not None and not isinstance(path, (str, bytes, os.PathLike)):
            raise ModelError(f"history must be a file path, a HistoryWriter or None, "
                             f"got {path!r} ({type(path).__name__})")
        if resume and path is None:
            raise ModelError("resume needs the history file of the interrupted run: give "
                             "history=FILE (command line: --history FILE)")
        self.path = None if path is None else os.fspath(path)
        self.records = []
        self.previous = []
        self.fingerprint = None
        self.options = None
        self.resume = bool(resume)
        self._fh = None
        if self.path is None:
            return
        existed = check_regular_file(self.path, "history")
        # opened without truncating, then locked: a second run on the same file is refused
        # before it can touch the first one's records
        self._fh = _locked(self.path)
        try:
            if resume and existed:
                self.previous = read_history(self.path)
                _whole_lines(self._fh)
            elif mode == "w":
                self._fh.truncate(0)
            self._fh.seek(0, os.SEEK_END)
        except BaseException:
            self.close()
            raise

    def check_fingerprint(self, fp, options=None):
        """Set the fingerprint (flexmbs.model.fingerprint.fingerprint) of what this history answers:
        written with the first record; when resuming from records, the file's must be the
        same, else ModelError naming the file and what differs (a history of another case,
        overrides, method, options or flexmbs version is never replayed). `options`: the
        run's options whole (plain data, flexmbs.model.options), written with the first
        record too (key ``options``, file only)."""
        if self.previous:
            diff = differences(self.previous[0].get("fingerprint"), fp)
            if diff:
                self.close()
                raise ModelError(
                    f"history {self.path!r} does not answer this run, so it cannot be "
                    f"resumed: {'; '.join(diff)}. Resume with the same case, overrides, "
                    "method and options, or start afresh without resume (or with another "
                    "history file)")
        self.fingerprint = fp
        self.options = options

    def write(self, record, file_extra=None):
        """Store a record (dict) and append it to the file as one JSON line; `file_extra`
        (dict) is added to the file's line only (large data, e.g. the evaluations a resumed
        run replays, not kept in `records`). When resuming, a record the file holds already
        is checked against it and not written again."""
        rec = jsonable(record)
        k = len(self.records)
        if k < len(self.previous):
            old = self.previous[k]
            if (old.get("iteration") != rec.get("iteration")
                    or old.get("design") != rec.get("design")):
                raise ModelError(
                    f"history {self.path!r}: the resumed run differs from the interrupted one at "
                    f"record {k + 1}: iteration {rec.get('iteration')}, design "
                    f"{rec.get('design')} where the file has iteration {old.get('iteration')}, "
                    f"design {old.get('design')}; resume with the same case, start and "
                    "options, or start afresh without resume")
            self.records.append(rec)
            return rec
        self.records.append(rec)
        if self._fh is not None:
            line = rec if not file_extra else dict(rec, **jsonable(file_extra))
            if k == 0 and self.fingerprint is not None:
                line = dict(line, fingerprint=jsonable(self.fingerprint))
            if k == 0 and self.options is not None:
                line = dict(line, options=jsonable(self.options))
            self._fh.write(json.dumps(line) + "\n")
            self._fh.flush()
            os.fsync(self._fh.fileno())
        return rec

    def close(self):
        if self._fh is not None:
            self._fh.close()
            self._fh = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def open_history(history, resume=False):
    """(writer, own) for an optimizer's `history` and `resume` options: a HistoryWriter of
    the given path (own=True: the optimizer closes it), or the HistoryWriter given (which must
    have been opened with resume=True when resume is asked). ModelError for a non-bool resume
    or resume without a history file."""
    if not isinstance(resume, bool):
        raise ModelError(f"resume must be True or False, got {resume!r}")
    if isinstance(history, HistoryWriter):
        if resume and not history.resume:
            raise ModelError("resume=True with a HistoryWriter: open it with "
                             "HistoryWriter(path, resume=True)")
        return history, False
    return HistoryWriter(history, resume=resume), True


def read_history(path):
    """The records of a history file written by HistoryWriter (list of dicts).

    A last line without its newline that is not valid JSON (a record cut short by a crash or a
    full disk) is skipped with a warning; an invalid line elsewhere raises ModelError naming
    the file and the line.
    """
    check_regular_file(path, "history")
    try:
        with open(path, encoding="utf-8") as fh:
            lines = fh.readlines()
    except UnicodeDecodeError as exc:
        raise ModelError(f"history {os.fspath(path)!r} is not a history (JSON lines written "
                         f"by flexmbs): not UTF-8 text at byte {exc.start}") from None
    out = []
    for k, line in enumerate(lines, 1):
        if not line.strip():
            continue
        try:
            out.append(json.loads(line))
        except ValueError:
            if k == len(lines) and not line.endswith("\n"):
                warnings.warn(f"history {os.fspath(path)!r}: last line {k} is cut short "
                              "(interrupted write), skipped", stacklevel=2)
                break
            raise ModelError(f"history {os.fspath(path)!r}: line {k} is not a JSON record: "
                             f"{line[:60]!r}") from None
    return out


@dataclass
class OptimizationResult:
    """Outcome of an optimization (weakly or fully coupled) of a problem.

    Attributes
    ----------
    method : 'weakly' or 'fully'.
    case : the case name.
    variables, units : names and units of the design variables.
    design : (nv,) final design (the variables' own units).
    start : (nv,) starting design.
    objective : the objective's value at `design`.
    objective_name : its response.
    mass_kg : mass of the design (the objective when it is a mass response, else the mass of
        every beam), or None.
    max_violation : max(0, max g) of the final design in a fresh full simulation (g relative
        to the limits: 1e-3 is 0.1 % beyond a limit).
    max_deviation_m : the largest value of the constrained deviation responses of the final
        design, or None when no deviation is constrained.
    iterations : cycles (weakly: MBS analyses) or optimizer iterations (fully).
    inner_iterations : summed iterations of the static problems (weakly), None (fully).
    evaluations : distinct designs analysed.
    simulations : full simulations run.
    converged, reason : the stopping test's verdict, in words.
    history : one record per cycle / iteration (see the module docstring).
    wall_time_s : wall time of the whole run.
    details : method-specific values (also written to JSON at the top level).
    t, deviation : time grid and constrained deviation history (nt,) of the final design
        (not in JSON); evaluation : the final `flexmbs.problem.Evaluation` (not in JSON).
    verification : the final design checked at converged resolution
        (`flexmbs.analysis.accuracy.Verification`; in JSON as details' ``verification``), or None when
        the run was not verified (verify=False).
    """
    method: str
    case: str
    variables: list
    units: list
    design: np.ndarray
    start: np.ndarray
    objective: float
    objective_name: str
    mass_kg: float | None
    max_violation: float | None
    max_deviation_m: float | None
    iterations: int
    inner_iterations: int | None
    evaluations: int
    simulations: int
    converged: bool
    reason: str
    history: list
    wall_time_s: float
    details: dict = field(default_factory=dict)
    t: np.ndarray | None = field(default=None, repr=False)
    deviation: np.ndarray | None = field(default=None, repr=False)
    evaluation: object = field(default=None, repr=False)
    verification: object = field(default=None, repr=False)

    @property
    def feasible(self):
        """All constraints of the final design hold: largest g <= FEASIBILITY_TOL
        (flexmbs.problem, relative to the limits)."""
        return is_feasible(self.max_violation)

    @property
    def verified(self):
        """The verification's verdict (details' ``verification``: the objective and every
        constraint settled to its rtol at a finer step), None when the run was not verified."""
        v = self.details.get("verification")
        return None if not v else bool(v["verified"])

    @property
    def verified_h(self):
        """The step (s) the verification settled the values on, None without a verification."""
        v = self.details.get("verification")
        return None if not v else float(v["h"])

    def to_dict(self, history=True):
        """A JSON-ready dict: the fields above, `details` merged at the top level."""
        d = dict(method=self.method, case=self.case, variables=self.variables, units=self.units,
                 design=self.design, start=self.start, objective=self.objective,
                 objective_name=self.objective_name, mass_kg=self.mass_kg,
                 max_violation=self.max_violation, max_deviation_m=self.max_deviation_m,
                 iterations=self.iterations, inner_iterations=self.inner_iterations,
                 evaluations=self.evaluations, simulations=self.simulations,
                 converged=self.converged, reason=self.reason, wall_time_s=self.wall_time_s,
                 feasible=self.feasible, feasibility_tol=FEASIBILITY_TOL,
                 verified=self.verified, verified_h=self.verified_h)
        for k, v in self.details.items():
            d.setdefault(k, v)
        if history:
            d["history"] = self.history
        return jsonable(d)

    def to_json(self, history=True, indent=None):
        """The result as a JSON string (see to_dict)."""
        return json.dumps(self.to_dict(history=history), indent=indent)

    def summary(self):
        """A few lines for people."""
        p = ", ".join(f"{n} = {v:.5g}{' ' + u if u else ''}" for n, v, u in
                      zip(self.variables, np.asarray(self.design, float), self.units))
        inner = ("" if self.inner_iterations is None
                 else f", {self.inner_iterations} inner iterations")
        unit = self.details.get("objective_unit")
        h = self.details.get("h")
        at = "" if h is None else f" at h = {h:.4g} s"
        lines = [f"{self.method} coupled, case {self.case}: "
                 f"{'converged' if self.converged else 'NOT converged'} ({self.reason})",
                 f"  design {p}",
                 f"  objective {self.objective_name} = {self.objective:.6g}"
                 f"{' ' + unit if unit else ''}{at}"]
        if self.max_violation is not None:
            lines.append(f"  constraints {'feasible' if self.feasible else 'INFEASIBLE'}{at}: "
                         f"max violation {self.max_violation:.2e} (the largest g above 0, g "
                         f"relative to the limits; feasible when <= {FEASIBILITY_TOL:g})")
        lines.append(f"  {self.iterations} iterations{inner}, {self.simulations} simulations, "
                     f"{self.wall_time_s:.2f} s")
        if self.details.get("optimizer_reason"):
            lines.append(f"  optimizer: {self.details['optimizer_reason']}")
        if self.details.get("gradient_method_reason"):
            lines.append(f"  gradients: {self.details['gradient_method_reason']}")
        ratios = self.details.get("static_to_simulated")
        if ratios:
            kinds = self.details.get("frame_kinds") or {}
            lines.append("  static form / simulation at this design: "
                         + ", ".join(f"{n} {'n/a' if v is None else f'{v:.3g}'}"
                                     for n, v in ratios.items())
                         + (" (frames: " + ", ".join(f"{b} {k}" for b, k in kinds.items())
                            + ")" if kinds else ""))
        if self.max_deviation_m is not None:
            lines.append(f"  max deviation in the full simulation "
                         f"{self.max_deviation_m * 1e3:.4f} mm")
        ver = describe_verification(self.details)   # with objective_unit
        if ver:
            lines.append(f"  {ver}")
        return "\n".join(lines)

    def plot(self, path, limit_m=None):
        """Figure (PNG/PDF by extension): objective per cycle/iteration and the constrained
        deviation history of the final design (the paper's Figs. 5, 6, 8); with element-wise
        design variables (names ``D[k]``) a third panel draws each one's profile along its
        beam (root element first), final and start."""
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        profiles = {}
        for k, name in enumerate(self.variables):
            base, sep, _ = name.partition("[")
            if sep:
                profiles.setdefault(base, []).append(k)
        ncol = 3 if profiles else 2
        fig, axes = plt.subplots(1, ncol, figsize=(5 * ncol, 4))
        ax1, ax2 = axes[0], axes[1]
        if profiles:
            ax3 = axes[2]
            # profiles 10 times smaller than the largest (a wall beside a diameter) on a
            # second axis, so that both can be read
            top = {b: float(np.max(np.abs(np.concatenate(
                [np.asarray(self.design)[ks], np.asarray(self.start)[ks]])))) for b, ks in
                profiles.items()}
            big = max(top.values())
            small = {b for b, v in top.items() if v < 0.1 * big}
            ax_small = ax3.twinx() if small and len(small) < len(profiles) else None
            lines = []
            for i, (base, ks) in enumerate(profiles.items()):
                color = f"C{i}"
                ax = ax_small if (ax_small is not None and base in small) else ax3
                idx = np.arange(1, len(ks) + 1)
                lines += ax.step(idx, np.asarray(self.design)[ks], where="mid", color=color,
                                 label=f"{base} [{self.units[ks[0]]}]"
                                 + (" (right axis)" if ax is ax_small else ""))
                ax.step(idx, np.asarray(self.start)[ks], where="mid", color=color, ls=":",
                        lw=0.8)
            ax3.set_xlabel("element (root first)")
            ax3.set_ylabel("design value")
            if ax_small is not None:
                ax_small.set_ylabel("design value (right axis)")
            ax3.set_title("element-wise design (dotted: start)")
            ax3.legend(lines, [ln.get_label() for ln in lines], loc="center left", fontsize=8)
            ax3.grid(True, alpha=0.3)
        its = [r.get("iteration", k + 1) for k, r in enumerate(self.history)]
        key = "mass_kg" if all(r.get("mass_kg") is not None for r in self.history) \
            else "objective"
        ax1.plot(its, [r.get(key) for r in self.history], "o-")
        ax1.set_xlabel("cycle" if self.method == "weakly" else "iteration")
        unit = self.details.get("objective_unit")
        ax1.set_ylabel("mass [kg]" if key == "mass_kg" else
                       f"{self.objective_name}{f' [{unit}]' if unit else ''}")
        ax1.set_title(f"{self.method} coupled: objective history")
        ax1.grid(True, alpha=0.3)
        if self.t is not None and self.deviation is not None:
            ax2.plot(self.t, np.asarray(self.deviation) * 1e3, lw=1)
            if limit_m is not None:
                ax2.axhline(limit_m * 1e3, color="k", ls="--", lw=0.8, label="limit")
                ax2.legend(loc="best")
            ax2.set_xlabel("time [s]")
            ax2.set_ylabel("deviation [mm]")
            ax2.set_title("final design: deviation in the full simulation")
        else:
            ax2.semilogy(its, [max(r.get("max_violation") or 0.0, 1e-16)
                               for r in self.history], "o-")
            ax2.set_xlabel("cycle" if self.method == "weakly" else "iteration")
            ax2.set_ylabel("max(0, max g)")
            ax2.set_title("constraint violation")
        ax2.grid(True, alpha=0.3)
        fig.tight_layout()
        try:
            return save_figure(fig, path, dpi=120)
        finally:
            plt.close(fig)
