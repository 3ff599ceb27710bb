"""What the flow and the mixing loops share: stop rules, progress, checkpoint schedules.

Each loop advances its own model (the flow solver one explicit step at a time, the
mixing one stored-phase interval at a time, in steps) and asks these parts, after every
step, whether to stop, to save or to show progress, so that ``max_steps`` and
``wall_time`` mean the same in both and are honoured within a step of being reached.
"""

from __future__ import annotations

import math
import os
import time
from dataclasses import dataclass, field

__all__ = ["CheckpointSchedule", "StopRules", "memory_limit", "progress_bar"]


def available_memory() -> float:
    """Bytes this machine has available now (MemAvailable), or inf where unknown."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return float(line.split()[1]) * 1024.0
    except OSError:
        pass
    return math.inf


def memory_limit(budget_mb: float) -> tuple[float, str]:
    """The bytes a run may hold: ``numerics.memory_budget_mb`` or what the machine has
    available, whichever is less, with words for a refusal that names it."""
    budget = float(budget_mb) * 2**20
    available = available_memory()
    if budget <= available:
        return budget, f"numerics.memory_budget_mb = {budget_mb:g}"
    return available, f"the {available / 2**20:.0f} MiB this machine has available"


@dataclass
class StopRules:
    """``max_steps`` and ``wall_time`` (seconds from ``started``), checked every step.

    Parameters
    ----------
    max_steps : int, optional
        Stop once this many steps are done (counted over resumes: the loop's own count).
    wall_time : float, optional
        Stop once this many wall-clock seconds have passed since ``started``.
    started : float
        ``time.perf_counter()`` at the start (default: when the rules are made).
    """

    max_steps: int | None = None
    wall_time: float | None = None
    started: float = field(default_factory=time.perf_counter)

    @property
    def deadline(self) -> float:
        """The perf_counter time of ``wall_time`` (inf without one)."""
        return math.inf if self.wall_time is None else self.started + self.wall_time

    def reason(self, steps: int) -> str | None:
        """``"max_steps"`` or ``"wall_time"`` once either is reached, else None."""
        if self.max_steps is not None and steps >= self.max_steps:
            return "max_steps"
        if time.perf_counter() >= self.deadline:
            return "wall_time"
        return None


@dataclass
class CheckpointSchedule:
    """When to save: every ``every`` units of the loop's clock (wall seconds for the
    flow, revolutions for the mixing), counted from ``start``."""

    every: float
    start: float = 0.0

    def __post_init__(self):
        self.next = self.start + self.every

    def resume_at(self, now: float) -> None:
        """Schedule the next save after ``now`` (a run resumed part way)."""
        whole = math.floor((now - self.start) / self.every + 1e-9)
        self.next = self.start + (whole + 1) * self.every

    def due(self, now: float) -> bool:
        """True once ``now`` reaches the next save; the one after is then scheduled."""
        if now < self.next - 1e-9 * max(abs(self.every), 1.0):
            return False
        self.resume_at(now)
        return True


def progress_bar(
    show: bool | None, total: float, unit: str, *, precision: int = 2, label: str | None = None
):
    """A tqdm bar on standard error (``show`` None: when it is a terminal); ``label``
    follows the counts (default: the unit)."""
    from tqdm.auto import tqdm

    show = os.isatty(2) if show is None else show
    return tqdm(
        total=round(total, 6),
        unit=unit,
        disable=not show,
        leave=False,
        bar_format=(
            f"{{l_bar}}{{bar}}| {{n:.{precision}f}}/{{total:.{precision}f}} {label or unit} "
            "[{elapsed}<{remaining}{postfix}]"
        ),
    )
