"""What is left to check in a session, and re-carrying after a fix: the Session's fourth layer (`Reviewing`, on
`annotator.carry.Carrying`).

Every pose carried to a step remembers its source (`carried_from`); a pose carried from one that has changed since is
stale (`is_stale`), and `recarry` carries the object again, from its fixed pose, to exactly the stale steps.
`to_check` / `next_to_check` list what needs a look (unset, unchecked, a poor fit by its stored verdict, stale,
interpenetrating), `progress` / `progress_table` / `unchecked` where the annotation stands.
"""

from __future__ import annotations

import numpy as np

from dsr_bench.annotator.carry import Carrying
from dsr_bench.annotator.scoring import _nan_score


class Reviewing(Carrying):
    """Re-carrying and what is left to check (see the module docstring)."""

    def carried_from(self, obj: int, step: int | None = None) -> tuple[int, np.ndarray] | None:
        """(source step, source pose (7,)) that object `obj`'s pose at a step was carried from, or None when the
        pose was set by hand (pick, place, previous, nudge, snap, confirm) or is unset."""
        rec = self.state.carried[self._step(step)][self._check_obj(obj)]
        return None if rec is None else (int(rec["step"]), np.asarray(rec["pose"], dtype=np.float64))

    def is_stale(self, obj: int, step: int | None = None) -> bool:
        """Whether object `obj`'s pose at a step was carried from a pose that has changed since (its source step
        now holds another pose: a fix there, or a re-carry of it)."""
        found = self.carried_from(obj, step)
        if found is None:
            return False
        now = self.state.pose(found[0], obj)
        return now is not None and not np.array_equal(now, found[1])

    def _recarry_plan(self, obj: int, step: int) -> list[tuple[int, int]]:
        """(step, source) to re-carry, in step order: see `stale_steps`."""
        source = self.carried_from(obj, step) if self.is_stale(obj, step) else None
        if source is not None:  # stale: carried, from a source that has changed since
            step = source[0]
        chain, affected, plan = {step}, set(), []
        for t in range(step + 1, self.num_steps + 1):
            rec = self.carried_from(obj, t)
            if rec is None or rec[0] not in chain:
                continue  # set by hand (or carried from elsewhere): its pose is the user's, it stops the chain
            chain.add(t)
            if rec[0] in affected or self.is_stale(obj, t):
                affected.add(t)
                plan.append((t, rec[0]))
        return plan

    def stale_steps(self, obj: int, step: int | None = None) -> list[int]:
        """The steps `recarry(obj, step)` would re-carry: the later steps whose pose of object `obj` was carried
        (directly or through other carried steps) from `step` (default the current one) and not set by hand since,
        where the pose it was carried from has changed (or a step before it in the chain is re-carried). When the
        pose at `step` is itself such a stale carried pose, the chain starts at its source and includes `step`."""
        return [t for t, _ in self._recarry_plan(self._check_obj(obj), self._step(step))]

    def recarry(self, obj: int, step: int | None = None) -> list[int]:
        """Carry object `obj` again, from its fixed pose, to the steps `stale_steps` lists, exactly as visiting
        each step did (keep it when the fit holds, else snap, search along the push, search the unexplained cloud),
        in step order, each from its (re-carried) source. One undoable action; the other objects and every pose
        set by hand stay as they are. Returns the re-carried steps ([] when nothing is stale)."""
        self._writable()
        obj = self._check_obj(obj)
        plan = self._recarry_plan(obj, self._step(step))
        if not plan:
            return []
        redone: dict[int, tuple] = {}
        changes = {}
        for t, source in plan:
            if source in redone:
                pose, status, score = redone[source]
            else:
                pose, status, score = self.state.pose(source, obj), str(self.state.status[source, obj]), None
            done, _ = self._carry_objects(t, {obj: (source, pose, score, status)})
            changes.update(done)
            new_pose, new_status, new_score = done[(t, obj)][:3]
            redone[t] = (np.asarray(new_pose, dtype=np.float64), new_status, _nan_score(new_score))
        self._commit("recarry", changes)
        return [t for t, _ in plan]

    def to_check(self) -> list[tuple[int, int, str]]:
        """(step, object, why) of every object at a visited step that needs a look, in step then object order:
        'unset', 'unchecked' (initialised), 'poor fit' (its last score failed the fit checks; confirmed poses are
        the user's call and are left out), 'carried from a changed pose' (`is_stale`, or carried from such a
        step) or 'interpenetrates object k' (with another object's pose as it is now, which may have changed since
        this object's score was taken)."""
        out = []
        stale = [self._stale_all(i) for i in range(self.num_objects)]
        for t in range(self.num_steps + 1):
            if not self.state.visited[t]:
                continue
            inside = self._interpenetrating(t)
            for i in range(self.num_objects):
                status, score = str(self.state.status[t, i]), self.state.scores[t][i]
                if status == "unset":
                    out.append((t, i, "unset"))
                elif status == "initialised":
                    out.append((t, i, "unchecked"))
                elif status != "confirmed" and score is not None and not score.get("accepted", True):
                    out.append((t, i, "poor fit"))
                elif status != "confirmed" and t in stale[i]:
                    out.append((t, i, "carried from a changed pose"))
                elif status != "confirmed" and i in inside:
                    out.append((t, i, f"interpenetrates object {inside[i] + 1}"))
        return out

    def _stale_all(self, obj: int) -> set[int]:
        """Steps whose pose of object `obj` is stale or carried (through carried steps) from a stale one."""
        affected: set[int] = set()
        for t in range(1, self.num_steps + 1):
            rec = self.carried_from(obj, t)
            if rec is not None and (rec[0] in affected or self.is_stale(obj, t)):
                affected.add(t)
        return affected

    def next_to_check(self) -> tuple[int, int, str] | None:
        """The first entry of `to_check` after the current step and selected object (wrapping around; the
        selected object itself comes last), or None when nothing at a visited step needs a look."""
        todo = self.to_check()
        if not todo:
            return None
        here = (self.state.step, self.state.selected)
        return next((e for e in todo if (e[0], e[1]) > here), todo[0])

    def progress(self) -> dict:
        """Per step and object: status and last fit score; steps done; action counts (JSON-able)."""
        steps = []
        for s in range(self.num_steps + 1):
            objs = [{"status": str(self.state.status[s, i]), "score": self.state.scores[s][i]}
                    for i in range(self.num_objects)]
            done = all(o["status"] in ("snapped", "confirmed") for o in objs)
            steps.append({"step": s, "visited": bool(self.state.visited[s]), "done": done, "objects": objs})
        return {"capture": self.capture.name, "num_steps": self.num_steps, "num_objects": self.num_objects,
                "current_step": self.step, "steps_done": sum(s["done"] for s in steps), "steps": steps,
                "action_counts": self.action_counts}

    def progress_table(self) -> str:
        """The progress as a text table: one row per step, one column per object (status, coverage, RMSE)."""
        p = self.progress()
        head = (f"capture {p['capture']}: {p['num_steps'] + 1} steps x {p['num_objects']} objects, "
                f"{p['steps_done']}/{p['num_steps'] + 1} steps done, current step {p['current_step']}")
        names = [f"{i + 1} {o.name}" for i, o in enumerate(self.capture.objects)]  # numbered from 1, as the panel
        width = 24
        lines = [head, "step  " + "".join(f"{n[:width - 2]:<{width}}" for n in names)]
        for s in p["steps"]:
            cells = []
            for o in s["objects"]:
                sc = o["score"]
                text = o["status"]
                if sc is not None and o["status"] != "unset":
                    rmse = sc.get("rmse")
                    text += f" {sc.get('coverage', 0):.0%}"
                    text += f" {rmse * 1000:.1f}mm" if isinstance(rmse, (int, float)) else " -"
                cells.append(f"{text:<{width}}")
            mark = ">" if s["step"] == p["current_step"] else " "
            lines.append(f"{mark}{s['step']:<4} " + "".join(cells))
        counts = ", ".join(f"{k} {v}" for k, v in p["action_counts"].items() if v)
        lines.append(f"actions: {counts or 'none'}")
        return "\n".join(lines)

    def unchecked(self) -> list[tuple[int, int, str]]:
        """(step, object, status) of every object not yet 'snapped' or 'confirmed'."""
        return [(s, i, str(self.state.status[s, i])) for s in range(self.num_steps + 1) for i in range(self.num_objects)
                if self.state.status[s, i] not in ("snapped", "confirmed")]
