"""Chamber programs: what the chamber setpoint and the tilt fixture do over a run (docs/physics.md).

A :class:`Program` is a list of stages, each a list of steps: :class:`Ramp` and :class:`Soak` of the chamber
setpoint (the unit stays in its last position), :class:`Move` to a position and :class:`Hold` of a position (the
setpoint stays), and :class:`Tour`: the fixture cycles through positions while the setpoint ramps or stays (the fast
programs of docs/physics.md, "Fast programs"). :meth:`Program.timetable` expands it into a :class:`Timetable` of
segments that answers vectorised questions for a time grid ``t_s`` (seconds since the start): setpoint, position per
sample, moves, fixture events.

Programs by name (:data:`PROGRAMS`), and :func:`parse_program` for a stepped program written as text
(``20@0:TP; -40@0:TP; -10@0:VP; ...``: setpoint C, soak min, positions per stage).

This timetable is the simulator's script only; the pipeline finds plateaus and positions from the data.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from pipeline.positions import (
    ALL_POSITIONS,
    MOVING,
    POSITION_NAMES,
    TEST_POSITIONS,
    VERIFICATION_POSITIONS,
)

TP = tuple(TEST_POSITIONS)
VP = tuple(VERIFICATION_POSITIONS)


@dataclass(frozen=True)
class Ramp:
    """Chamber setpoint ramps linearly from its current value to ``to_c`` at ``rate_c_per_min``."""

    to_c: float
    rate_c_per_min: float = 1.0


@dataclass(frozen=True)
class Soak:
    """Chamber setpoint held for ``duration_s``; the unit stays where it is."""

    duration_s: float


@dataclass(frozen=True)
class Move:
    """The fixture turns the unit to ``to_position`` in ``duration_s`` (no-op if already there)."""

    to_position: str
    duration_s: float = 20.0


@dataclass(frozen=True)
class Hold:
    """The unit is held static in ``position`` (which must be the current one) for ``duration_s``."""

    position: str
    duration_s: float = 300.0


@dataclass(frozen=True)
class Tour:
    """The fixture cycles through ``positions`` (each held ``hold_s``, with moves of ``move_s`` between them) while
    the chamber setpoint ramps to ``to_c`` at ``rate_c_per_min``, or, with ``to_c`` None, stays where it is for
    ``duration_s``. The cycle goes on from the position the unit is in: a tour that follows a hold moves on to the
    next one in ``positions`` (the first when the unit is in none of them), otherwise it holds the position it is
    in first; the last hold of the step lasts to the step's end (a hold that would leave less than a move and a
    hold is stretched instead)."""

    positions: tuple[str, ...]
    to_c: float | None = None
    rate_c_per_min: float = 1.0
    duration_s: float = 0.0
    hold_s: float = 120.0
    move_s: float = 20.0


Step = Ramp | Soak | Move | Hold | Tour


@dataclass(frozen=True)
class Stage:
    label: str
    steps: tuple[Step, ...]


@dataclass(frozen=True)
class Segment:
    """One piece of the expanded program: ``kind`` is ``ramp``, ``soak``, ``move`` or ``hold``.

    ``position`` is the position during the segment (``MOVING`` for a move, which goes from ``from_position`` to
    ``to_position``; both equal ``position`` otherwise). The setpoint goes linearly from ``setpoint_start_c`` to
    ``setpoint_end_c``. ``stage`` is the index of the program stage.
    """

    kind: str
    t_start_s: float
    t_end_s: float
    setpoint_start_c: float
    setpoint_end_c: float
    position: str
    from_position: str
    to_position: str
    stage: int


@dataclass(frozen=True)
class Program:
    """A chamber program. The unit starts at ``start_setpoint_c`` (soaked) in ``start_position``.

    ``case_lag_s`` and ``air_lag_s`` are the simulator's defaults for this program: the first-order lags of the AU
    case behind the chamber air and of the air behind the setpoint.
    """

    name: str
    stages: tuple[Stage, ...]
    start_setpoint_c: float = 20.0
    start_position: str = "TP1"
    case_lag_s: float = 600.0
    air_lag_s: float = 90.0

    def steps(self) -> list[Step]:
        return [s for stage in self.stages for s in stage.steps]

    def timetable(self) -> Timetable:
        """Expand into segments; zero-length ramps and moves to the current position are dropped."""
        t, sp, pos = 0.0, float(self.start_setpoint_c), self.start_position
        _check_position(pos)
        segs: list[Segment] = []
        for k, stage in enumerate(self.stages):
            for step in stage.steps:
                if isinstance(step, Ramp):
                    if step.rate_c_per_min <= 0:
                        raise ValueError(f"ramp rate must be positive, got {step.rate_c_per_min}")
                    dur = abs(step.to_c - sp) / step.rate_c_per_min * 60.0
                    if dur > 0:
                        segs.append(Segment("ramp", t, t + dur, sp, float(step.to_c), pos, pos, pos, k))
                    sp = float(step.to_c)
                elif isinstance(step, Soak):
                    dur = _duration(step)
                    segs.append(Segment("soak", t, t + dur, sp, sp, pos, pos, pos, k))
                elif isinstance(step, Move):
                    _check_position(step.to_position)
                    if step.to_position == pos:
                        continue
                    dur = _duration(step)
                    segs.append(Segment("move", t, t + dur, sp, sp, MOVING, pos, step.to_position, k))
                    pos = step.to_position
                elif isinstance(step, Hold):
                    if step.position != pos:
                        raise ValueError(f"Hold {step.position} while the unit is in {pos}: add a Move first")
                    dur = _duration(step)
                    segs.append(Segment("hold", t, t + dur, sp, sp, pos, pos, pos, k))
                elif isinstance(step, Tour):
                    held = bool(segs) and segs[-1].kind == "hold" and segs[-1].t_end_s == t
                    tour, dur, pos = _tour_segments(step, t, sp, pos, k, held)
                    segs += tour
                    sp = float(step.to_c) if step.to_c is not None else sp
                else:
                    raise TypeError(f"unknown program step {step!r}")
                t += dur
        return Timetable(
            tuple(s for s in segs if s.t_end_s > s.t_start_s), self.start_position, float(self.start_setpoint_c)
        )


def _duration(step: Soak | Move | Hold | Tour) -> float:
    dur = float(step.duration_s)
    if not dur >= 0:
        raise ValueError(f"duration must be >= 0 s in {step!r}")
    return dur


def _tour_segments(
    step: Tour, t0: float, sp0: float, pos: str, stage: int, held: bool
) -> tuple[list[Segment], float, str]:
    """The hold and move segments of a :class:`Tour` starting at ``t0`` (s) from setpoint ``sp0`` (C) in ``pos``
    (``held``: its hold has just ended, so the tour moves on at once): (segments, duration s, the position it ends
    in). The setpoint runs linearly over the whole step."""
    if not step.positions:
        raise ValueError("a tour needs at least one position")
    for p in step.positions:
        _check_position(p)
    if not (step.hold_s > 0 and step.move_s >= 0):
        raise ValueError(f"a tour needs hold_s > 0 and move_s >= 0, got {step.hold_s} and {step.move_s}")
    if step.to_c is None:
        dur = _duration(step)
        to_c = sp0
    else:
        if not step.rate_c_per_min > 0:
            raise ValueError(f"ramp rate must be positive, got {step.rate_c_per_min}")
        to_c = float(step.to_c)
        dur = abs(to_c - sp0) / step.rate_c_per_min * 60.0
    t_end = t0 + dur

    def sp_at(t: float) -> float:
        return sp0 + (to_c - sp0) * (t - t0) / dur if dur > 0 else sp0

    segs: list[Segment] = []
    names = list(step.positions)
    nxt = (names.index(pos) + 1) % len(names) if pos in names else 0
    t = t0
    if pos not in names or (held and len(names) > 1):  # go on to the tour's next position at once
        end = min(t + step.move_s, t_end)
        segs.append(Segment("move", t, end, sp_at(t), sp_at(end), MOVING, pos, names[nxt], stage))
        t, pos, nxt = end, names[nxt], (nxt + 1) % len(names)
    while t < t_end:
        hold_end = t + step.hold_s
        if t_end - hold_end < step.move_s + step.hold_s or len(names) == 1:
            hold_end = t_end  # the last hold of the step lasts to its end
        segs.append(Segment("hold", t, hold_end, sp_at(t), sp_at(hold_end), pos, pos, pos, stage))
        t = hold_end
        if t >= t_end:
            break
        end = t + step.move_s
        segs.append(Segment("move", t, end, sp_at(t), sp_at(end), MOVING, pos, names[nxt], stage))
        t, pos, nxt = end, names[nxt], (nxt + 1) % len(names)
    return segs, dur, pos


def _check_position(name: str) -> None:
    if name not in ALL_POSITIONS:
        raise ValueError(f"unknown position {name!r}; expected one of {', '.join(POSITION_NAMES)}")


def visit(positions, hold_s: float = 300.0, move_s: float = 20.0) -> tuple[Step, ...]:
    """Move to and hold each position in turn (the move is dropped where the unit is already there)."""
    return tuple(s for p in positions for s in (Move(p, move_s), Hold(p, hold_s)))


@dataclass(frozen=True)
class Timetable:
    """The expanded program. All queries are vectorised over a time grid ``t_s`` (s since the start)."""

    segments: tuple[Segment, ...]
    start_position: str
    start_setpoint_c: float

    @property
    def duration_s(self) -> float:
        return self.segments[-1].t_end_s if self.segments else 0.0

    def _starts(self) -> np.ndarray:
        return np.array([s.t_start_s for s in self.segments])

    def _index(self, t_s) -> np.ndarray:
        """Segment index of each time; a segment owns [t_start, t_end)."""
        return np.clip(
            np.searchsorted(self._starts(), np.asarray(t_s, float), side="right") - 1, 0, len(self.segments) - 1
        )

    def setpoint_c(self, t_s) -> np.ndarray:
        """Chamber setpoint (C), piecewise linear."""
        knots = [self.segments[0].t_start_s] + [s.t_end_s for s in self.segments]
        values = [self.segments[0].setpoint_start_c] + [s.setpoint_end_c for s in self.segments]
        return np.interp(np.asarray(t_s, float), knots, values)

    def position_index(self, t_s) -> np.ndarray:
        """Nominal position per sample as an index into ``positions.POSITION_NAMES``; -1 while moving."""
        table = np.array([POSITION_NAMES.index(s.position) if s.position != MOVING else -1 for s in self.segments])
        return table[self._index(t_s)]

    def positions(self, t_s) -> np.ndarray:
        """Nominal position name per sample (``MOVING`` during moves), as an object array."""
        names = np.array(list(POSITION_NAMES) + [MOVING], dtype=object)
        return names[self.position_index(t_s)]

    def moves(self) -> list[Segment]:
        return [s for s in self.segments if s.kind == "move"]

    def move_times_s(self) -> tuple[np.ndarray, np.ndarray]:
        """Start and end (arrival) times of every move, s."""
        mv = self.moves()
        return np.array([s.t_start_s for s in mv]), np.array([s.t_end_s for s in mv])

    def fixture_events(self) -> list[tuple[float, str]]:
        """What the tilt controller logs, (t_s, position): the start position at 0, then ``MOVING`` at each move
        start and the new position at its arrival."""
        events = [(0.0, self.start_position)]
        for s in self.moves():
            events += [(s.t_start_s, MOVING), (s.t_end_s, s.to_position)]
        return events

    def holds(self) -> list[Segment]:
        """The static position holds (Hold steps) in time order."""
        return [s for s in self.segments if s.kind == "hold"]

    def ramp_sign(self, t_s) -> np.ndarray:
        """Direction the temperature last came from: +1 from the start of a heating ramp on, -1 from a cooling
        ramp, 0 before the first ramp (docs/physics.md, thermal_hysteresis). A ramp is any segment whose setpoint
        changes (a ramp step, or the holds and moves of a tour on a ramp)."""
        sign = np.zeros(len(self.segments))
        last = 0.0
        for i, s in enumerate(self.segments):
            if s.setpoint_end_c != s.setpoint_start_c:
                last = float(np.sign(s.setpoint_end_c - s.setpoint_start_c))
            sign[i] = last
        return sign[self._index(t_s)]

    def stage_index(self, t_s) -> np.ndarray:
        return np.array([s.stage for s in self.segments])[self._index(t_s)]


def _temperature_program(
    name: str,
    soak_s: tuple[float, float],
    hold_s: float,
    move_s: float,
    rate_c_per_min: float,
    case_lag_s: float,
    air_lag_s: float,
) -> Program:
    """The seven stages of docs/physics.md with the given timings; soak_s = (normal soak, long soak at -40/+70 C)."""
    soak, long_soak = soak_s
    plan = [  # (setpoint C, soak s, positions)
        (20.0, soak, TP),
        (-40.0, long_soak, TP),
        (-10.0, soak, VP),
        (20.0, soak, TP + VP),
        (45.0, soak, VP),
        (70.0, long_soak, TP),
        (20.0, soak, TP + VP),
    ]
    stages = tuple(
        Stage(f"{sp:+.0f} C", (Ramp(sp, rate_c_per_min), Soak(sk)) + visit(pos, hold_s, move_s)) for sp, sk, pos in plan
    )
    return Program(
        name, stages, start_setpoint_c=20.0, start_position="TP1", case_lag_s=case_lag_s, air_lag_s=air_lag_s
    )


def standard_program() -> Program:
    """docs/physics.md "The standard chamber program": 7 stages, holds 300 s, moves 20 s, ramps 1 C/min, soaks 60 min
    (90 min at -40 and +70 C); about 16.5 h. Case lag 600 s."""
    return _temperature_program(
        "standard", (3600.0, 5400.0), hold_s=300.0, move_s=20.0, rate_c_per_min=1.0, case_lag_s=600.0, air_lag_s=90.0
    )


def short_program() -> Program:
    """The standard sequence of temperatures and positions, short: soaks 15 min, holds 60 s, moves 10 s, ramps
    5 C/min (about 3.5 h). Case lag 120 s."""
    return _temperature_program(
        "short", (900.0, 900.0), hold_s=60.0, move_s=10.0, rate_c_per_min=5.0, case_lag_s=120.0, air_lag_s=30.0
    )


def differential_program(orientations=("TP1", "TP2", "TP3", "TP4", "TP5", "TP6")) -> Program:
    """Seed 003's differential method: in each orientation (default the paper's six) the unit is held at +20 C
    for 30 min, then the chamber cycles +20 -> -40 -> +70 -> +20 C at 1 C/min with 30 min soaks at each end,
    without moving. Case lag 600 s. Imprecise orientations: add ``--effect fixture_face_error:sigma_deg=1.5``.
    """
    stages = []
    for p in orientations:
        steps = (
            Move(p, 20.0),
            Hold(p, 1800.0),
            Ramp(-40.0),
            Soak(1800.0),
            Ramp(70.0),
            Soak(1800.0),
            Ramp(20.0),
            Soak(1800.0),
        )
        stages.append(Stage(f"cycle in {p}", steps))
    return Program(
        "differential", tuple(stages), start_setpoint_c=20.0, start_position="TP1", case_lag_s=600.0, air_lag_s=90.0
    )


def handheld_program(rounds: int = 3, hold_s: float = 3.0, move_s: float = 1.5) -> Program:
    """A hand-turned multi-face fixture at room temperature (docs/physics.md, "Real recordings"): the unit is turned by
    hand through the twelve positions (TP1..TP6, VP1..VP6) ``rounds`` times in a shuffled order, each pose held
    ``hold_s`` (3 s) with ``move_s`` (1.5 s) turns between them; the setpoint stays at 20 C (no ramp). Default:
    36 poses in about 2.7 min. Simulate it at ~100 Hz with timestamp jitter (``SimConfig.jitter_s``)."""
    order = np.random.default_rng(13).permuted(np.tile(np.arange(len(POSITION_NAMES)), (rounds, 1)), axis=1)
    names = [POSITION_NAMES[i] for i in order.ravel()]
    names = [n for k, n in enumerate(names) if k == 0 or n != names[k - 1]]  # no pose repeated back to back
    steps = (Hold(names[0], hold_s),) + visit(names[1:], hold_s, move_s)
    return Program(
        "handheld",
        (Stage("poses at 20 C", steps),),
        start_setpoint_c=20.0,
        start_position=names[0],
        case_lag_s=120.0,
        air_lag_s=30.0,
    )


def sweep_program(
    orientations=("TP3", "TP5", "TP2"),
    cold_c: float = 5.0,
    warm_c: float = 25.0,
    cool_c_per_min: float = 0.75,
    warm_c_per_min: float = 0.05,
) -> Program:
    """A temperature sweep with few orientations (docs/physics.md, "Real recordings"; the shape of a logger put in a
    fridge): in each orientation (default three, one axis vertical in each, pointing down) the unit cools from
    where it is to ``cold_c`` at ``cool_c_per_min`` and warms slowly to ``warm_c`` at ``warm_c_per_min``, never
    holding a plateau. About 7.2 h per orientation with the defaults. Case lag 600 s."""
    stages = tuple(
        Stage(f"sweep in {p}", (Move(p, 20.0), Ramp(cold_c, cool_c_per_min), Ramp(warm_c, warm_c_per_min)))
        for p in orientations
    )
    return Program(
        "sweep", stages, start_setpoint_c=20.0, start_position=orientations[0], case_lag_s=600.0, air_lag_s=90.0
    )


def fast_program(
    low_c: float = -40.0,
    high_c: float = 70.0,
    rate_c_per_min: float = 1.5,
    dwell_s: float = 1800.0,
    hold_s: float = 240.0,
    move_s: float = 20.0,
    positions: tuple[str, ...] = TP + VP,
) -> Program:
    """Positions held on continuous ramps up and then down (docs/physics.md, "Fast programs"; Niu et al. 2013): from
    +20 C (soaked) the setpoint ramps to ``high_c``, stays there ``dwell_s``, ramps down to ``low_c``, stays
    ``dwell_s`` and ramps back to +20 C, all at ``rate_c_per_min``, while the fixture cycles through ``positions``
    the whole time (holds ``hold_s``, moves ``move_s``). Every temperature between the ends is passed once heating
    and once cooling; the dwells let the case reach the ends (its lag behind the air is 600 s, as in the standard
    program). Defaults: 1.5 C/min, 30-min dwells, 240-s holds, 20-s moves, TP1..TP6 and VP1..VP6: 3.44 h, a fifth
    of the standard program (benchmarks/fast_programs.py: shorter holds or faster ramps leave the VP errors at
    the noise floor twice the standard program's)."""
    if not low_c < 20.0 < high_c:
        raise ValueError(f"a fast program runs from +20 C to its ends, which must lie either side: {low_c}..{high_c}")
    if not dwell_s >= 0:
        raise ValueError(f"dwell must be >= 0 s, got {dwell_s}")

    def tour(**kw) -> Tour:
        return Tour(tuple(positions), hold_s=hold_s, move_s=move_s, rate_c_per_min=rate_c_per_min, **kw)

    plan = [
        (f"up to {high_c:+.0f} C", tour(to_c=high_c)),
        (f"at {high_c:+.0f} C", tour(duration_s=dwell_s)),
        (f"down to {low_c:+.0f} C", tour(to_c=low_c)),
        (f"at {low_c:+.0f} C", tour(duration_s=dwell_s)),
        ("up to +20 C", tour(to_c=20.0)),
    ]
    stages = tuple(Stage(label, (step,)) for label, step in plan if step.to_c is not None or dwell_s > 0)
    return Program("fast", stages, start_setpoint_c=20.0, start_position=positions[0], case_lag_s=600.0, air_lag_s=90.0)


#: the position groups a stepped program's text may name besides single positions
POSITION_GROUPS = {"TP": TP, "VP": VP}


def parse_program(
    spec: str,
    rate_c_per_min: float = 1.0,
    hold_s: float = 300.0,
    move_s: float = 20.0,
    case_lag_s: float = 600.0,
    air_lag_s: float = 90.0,
) -> Program:
    """A stepped program written as text: stages separated by ``;``, each ``SETPOINT@SOAK:POSITIONS`` (setpoint in
    C, soak in minutes after the ramp to it, the positions visited then: ``TP``, ``VP``, ``TP3``, ... joined by
    ``+``), e.g. ``20@0:TP; -40@0:TP; -10@0:VP; 20@0:TP+VP; 45@0:VP; 70@0:TP; 20@0:TP+VP`` (issue 23: no soak, the
    positions held while the unit still approaches each temperature). ``@SOAK`` may be left out (no soak). Ramps at
    ``rate_c_per_min``, holds ``hold_s``, moves ``move_s``; the unit starts soaked at the first stage's setpoint in
    its first position. ValueError naming the stage at fault."""
    stages = []
    texts = [x.strip() for x in spec.split(";") if x.strip()]
    if not texts:
        raise ValueError(f"a program needs at least one stage SETPOINT@SOAK:POSITIONS, got {spec!r}")
    for text in texts:
        head, sep, pos_text = text.partition(":")
        sp_text, _, soak_text = head.partition("@")
        try:
            sp = float(sp_text.strip().removesuffix("C").removesuffix("c"))
            soak_min = float(soak_text) if soak_text.strip() else 0.0
        except ValueError:
            sp = soak_min = float("nan")
        if not sep or not np.isfinite(sp) or not soak_min >= 0:
            raise ValueError(f"stage {text!r}: expected SETPOINT@SOAK_MIN:POSITIONS, e.g. -40@0:TP")
        names: list[str] = []
        for part in pos_text.split("+"):
            key = part.strip().upper()
            group = POSITION_GROUPS.get(key)
            if group is None and key not in ALL_POSITIONS:
                raise ValueError(f"stage {text!r}: unknown position {part.strip()!r} (TP, VP, TP1..TP6, VP1..VP6)")
            names += list(group or (key,))
        soak = (Soak(soak_min * 60.0),) if soak_min > 0 else ()
        stages.append(Stage(f"{sp:+.0f} C", (Ramp(sp, rate_c_per_min), *soak) + visit(names, hold_s, move_s)))
    start_position = next(st.to_position for st in stages[0].steps if isinstance(st, Move))
    return Program(
        "stepped",
        tuple(stages),
        start_setpoint_c=next(float(st.to_c) for st in stages[0].steps if isinstance(st, Ramp)),
        start_position=start_position,
        case_lag_s=case_lag_s,
        air_lag_s=air_lag_s,
    )


def parse_drop(spec: str) -> tuple[str, float, int | None]:
    """``POS@T`` or ``POS@T#K`` (e.g. ``TP4@-40``, ``VP3@+20#2``): the position, the stage setpoint (C) and which
    of the stages at that setpoint (1, 2, ...; None: every one). ValueError naming what is wrong."""
    text = spec.strip()
    pos, sep, rest = text.partition("@")
    if not sep:
        raise ValueError(f"expected POSITION@TEMPERATURE[#K] (e.g. TP4@-40), got {spec!r}")
    pos = pos.strip().upper()
    _check_position(pos)
    temp, _, k = rest.partition("#")
    try:
        temp_c = float(temp.strip().removesuffix("C").removesuffix("c").strip())
        nth = int(k) if k.strip() else None
    except ValueError:
        raise ValueError(f"expected POSITION@TEMPERATURE[#K] (e.g. TP4@-40), got {spec!r}") from None
    if nth is not None and nth < 1:
        raise ValueError(f"the stage number after # counts from 1, got {spec!r}")
    return pos, temp_c, nth


def variant(program: Program, soak_s: float | None = None, drop: tuple[str, ...] = ()) -> Program:
    """``program`` with every soak lasting ``soak_s`` (None: as it is; 0: none, the positions follow the ramp at
    once) and the hold of each position in ``drop`` (:func:`parse_drop` specs: ``TP4@-40``) left out of the stages
    at that setpoint (with its move): short-soak and missing-position programs (issue 14), made from the standard
    one or any other. ValueError when a soak is negative or a dropped position is not held at that setpoint."""
    if soak_s is not None and not soak_s >= 0:
        raise ValueError(f"soak must be >= 0 s, got {soak_s}")
    drops = [(spec, *parse_drop(spec)) for spec in drop]
    used = {spec: False for spec, *_ in drops}
    seen: dict[float, int] = {}
    sp = float(program.start_setpoint_c)
    stages = []
    for stage in program.stages:
        for step in stage.steps:
            if isinstance(step, Ramp):
                sp = float(step.to_c)
        seen[sp] = seen.get(sp, 0) + 1
        gone = set()
        for spec, pos, temp_c, nth in drops:
            if (
                abs(temp_c - sp) < 0.5
                and nth in (None, seen[sp])
                and any(isinstance(st, Hold) and st.position == pos for st in stage.steps)
            ):
                gone.add(pos)
                used[spec] = True
        steps: list[Step] = []
        for step in stage.steps:
            if isinstance(step, Soak) and soak_s is not None:
                if soak_s > 0:
                    steps.append(Soak(float(soak_s)))
            elif (
                isinstance(step, (Move, Hold))
                and (step.to_position if isinstance(step, Move) else step.position) in gone
            ):
                continue
            else:
                steps.append(step)
        stages.append(Stage(stage.label, tuple(steps)))
    missing = [spec for spec, ok in used.items() if not ok]
    if missing:
        raise ValueError(f"program {program.name!r} holds no such position at that setpoint: {', '.join(missing)}")
    name = (
        program.name
        + (f"+soak{soak_s / 60:g}min" if soak_s is not None else "")
        + "".join(f"-{spec.strip()}" for spec in drop)
    )
    return Program(
        name, tuple(stages), program.start_setpoint_c, program.start_position, program.case_lag_s, program.air_lag_s
    )


PROGRAMS = {
    "standard": standard_program,
    "short": short_program,
    "differential": differential_program,
    "handheld": handheld_program,
    "sweep": sweep_program,
    "fast": fast_program,
}


#: the programs whose ramp rate, holds and moves can be chosen (:func:`program_from`)
TIMED = ("fast",)


def program_from(
    name: str,
    rate_c_per_min: float | None = None,
    hold_s: float | None = None,
    move_s: float | None = None,
    soak_s: float | None = None,
    drop: tuple[str, ...] = (),
) -> Program:
    """The program ``thermocal simulate --program`` names: a name of :data:`PROGRAMS` or a stepped program's text
    (:func:`parse_program`, recognised by its ``:``), with the ramp rate (C/min), holds and moves (s) where given
    (the fast program and stepped programs only), every soak made ``soak_s`` (s; the fast program: its dwells at
    the ends) and positions dropped (:func:`variant`). ValueError naming what is wrong."""
    timing: dict[str, Any] = {
        k: v for k, v in (("rate_c_per_min", rate_c_per_min), ("hold_s", hold_s), ("move_s", move_s)) if v is not None
    }
    for k, v in timing.items():
        if not np.isfinite(v) or (not v > 0 and not (k == "move_s" and v == 0)):
            raise ValueError(f"{k} must be a finite number above 0{' (or 0)' if k == 'move_s' else ''}, got {v:g}")
    if ":" in name:
        program = parse_program(name, **timing)
    elif name in TIMED:
        dwell: dict[str, Any] = {"dwell_s": soak_s} if soak_s is not None else {}
        program = fast_program(**timing, **dwell)
        soak_s = None
    elif name in PROGRAMS:
        if timing:
            raise ValueError(
                f"ramp rate, holds and moves can be chosen for {', '.join(TIMED)} and stepped programs "
                f"(SETPOINT@SOAK:POSITIONS; ...), not for {name!r}"
            )
        program = get_program(name)
    else:
        raise ValueError(
            f"unknown chamber program {name!r}; expected one of {', '.join(PROGRAMS)} or a stepped program "
            "(SETPOINT@SOAK_MIN:POSITIONS; ..., e.g. 20@0:TP; -40@0:TP)"
        )
    if soak_s is not None or drop:
        program = variant(program, soak_s, tuple(drop))
    return program


def get_program(name: str | Program) -> Program:
    """The program called ``name``: ``standard``, ``short``, ``differential``, ``handheld``, ``sweep`` or ``fast``
    (a :class:`Program` is itself)."""
    if isinstance(name, Program):
        return name
    try:
        return PROGRAMS[name]()
    except KeyError:
        raise ValueError(f"unknown chamber program {name!r}; expected one of {', '.join(PROGRAMS)}") from None
