"""Skill samples from kinesthetic demonstrations: a person guides the arm through task
instances while a bag records its joint states; each demonstration becomes a sample
(tau, theta) of the skill.

The reference chapter: "Each training sample has to be gathered by kinesthetic teaching or
policy optimization". This module turns a recording into such samples:

1. `read_joint_states`: the task's joints (by name, `psl_task.joint_selection`) of every
   sensor_msgs/JointState on a topic of a rosbag2 bag (MCAP or sqlite3, as `psl record` and
   ``ros2 bag record`` write it), on the robot's clock (header stamps).
2. The recording is cut into demonstrations. A bag of rollouts through psl's graph holds the
   episodes psl announced (psl_msgs/TaskInstance on the tau topic, each stamped with its
   first state and carrying its length: `announces_episodes`): `episodes` takes the movement
   of each, with its tau (the announced ones that are none, e.g. homing episodes, and motions
   in no announced episode are said). Cutting from rest to rest cannot separate them: an
   episode's settling leaves the arm at rest for less than MIN_REST before the next one
   begins, and a teleport reset, a jump between two states, begins the next motion at the
   goal of the episode before.
   Otherwise (guided demonstrations) `rest_to_rest` cuts the spans in which the arm moves
   (the largest joint speed, a difference over 50 ms, above ``velocity_threshold``; pauses
   under 0.2 s belong to the motion), each from the rest before to the rest after, kept if
   it lasts ``min_duration``; or `windows` takes given time spans.
   A person brings the arm back to the start between two demonstrations: those returns
   (motions that end at the start posture from elsewhere, `split_returns`) are no
   demonstrations (said, given no tau, not refused).
3. `instance_at`: each demonstration's tau, given (in order), or from a topic in the same bag:
   the last instance announced at or before the arm starts to move (`motion_start`;
   psl_msgs/TaskInstance of the episode, homing episodes skipped, or
   std_msgs/Float64MultiArray of a perception node).
4. `teach_one` fits theta for the task's policy (`TaskPolicy.fit_demonstration`: the DMP's
   weights and, with a learned goal, its goal; joint or end-effector space) and checks it:
   the demonstration starts within ``start_tolerance`` of the start posture, the fitted
   movement reproduces it within ``fit_tolerance`` (max over joints and time, the
   demonstration's time mapped onto the movement's), the reference passes the task's safety
   check, tau is valid. A demonstration that fails is refused with the reason; nothing of it
   enters the skill.

`teach` does all of it and adds the accepted samples to a `SkillMemory` (in memory: the
caller saves the file, atomically, or sends the samples to the memory node). Imports no ROS:
bags are read with `rosbags` (`psl_ros.bag_reading`: a damaged, cut short or empty bag is one
ValueError naming it).
"""
from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from psl_controller.policy import TaskPolicy
from psl_task.arm_model import ArmModel
from psl_task.joint_selection import JointSelection
from psl_task.safety_check import SafetyCheck
from psl_task.task import TaskDefinition, TaskError, task_id

VELOCITY_THRESHOLD = 0.05     # rad/s: the arm rests while no joint moves faster
MIN_DURATION = 0.5            # s: a shorter motion is no demonstration (a nudge, a tremor)
MIN_REST = 0.2                # s: a shorter pause is part of the motion
VELOCITY_WINDOW = 0.05        # s: the joint speed is a difference over this span
START_TOLERANCE = 0.05        # rad: how far a demonstration may start from the start posture
FIT_TOLERANCE = 0.05          # rad: how far the fitted movement may stay from the demonstration
MAX_MESSAGES = 2_000_000      # joint states read from a bag at most (an hour at 500 Hz)
JOINT_STATE = 'sensor_msgs/msg/JointState'


@dataclasses.dataclass(frozen=True)
class Recording:
    """Joint angles q (N, n) of the task's joints at times t (N,) [s, the robot's clock]."""

    t: np.ndarray
    q: np.ndarray


@dataclasses.dataclass(frozen=True)
class Outcome:
    """What became of one demonstration: its span [start, end] s in the recording, tau,
    theta (None if refused), the fit's largest error [rad] and why it was refused ('' if
    not)."""

    start: float
    end: float
    tau: np.ndarray | None
    theta: np.ndarray | None
    fit_error: float
    reason: str = ''

    @property
    def accepted(self) -> bool:
        return self.theta is not None


def _stamp(msg, timestamp: int) -> float:
    header = getattr(msg, 'header', None)
    stamp = getattr(header, 'stamp', None) or getattr(msg, 'stamp', None)
    if stamp is None or (stamp.sec == 0 and stamp.nanosec == 0):
        return timestamp * 1e-9
    return stamp.sec + stamp.nanosec * 1e-9


def _messages(bag: str | Path, topic: str, typestore=None, msgtypes: tuple[str, ...] = ()):
    """(seconds, message) of every message on `topic` of the bag, in the bag's order.

    Raises:
        BagError (a ValueError naming the bag): the bag cannot be read (damaged, cut short,
            empty, not a bag: `psl_ros.bag_reading.open_bag`), has no such topic, the topic is
            of a type psl cannot decode or not one of `msgtypes` (when given), or it holds
            more than MAX_MESSAGES messages.
    """
    from psl_ros.bag_reading import BagError, open_bag
    from rosbags.typesys import Stores, get_typestore
    store = typestore or get_typestore(Stores.ROS2_JAZZY)
    with open_bag(bag) as reader:
        connections = [c for c in reader.connections if c.topic == topic]
        if not connections:
            raise BagError(f'{bag}: no topic {topic!r} (it has '
                           f'{", ".join(sorted(reader.topics)) or "none"})')
        for connection in connections:
            if msgtypes and connection.msgtype not in msgtypes:
                raise BagError(f'{bag}: {topic} holds {connection.msgtype}, not '
                               f'{" or ".join(msgtypes)}')
            if connection.msgtype not in store.types:
                raise BagError(f'{bag}: {topic} holds {connection.msgtype}, a type psl does '
                               'not know (its package is not installed here)')
        for count, (connection, timestamp, raw) in enumerate(reader.messages(connections)):
            if count >= MAX_MESSAGES:
                raise BagError(f'{bag}: more than {MAX_MESSAGES} messages on {topic}: cut '
                               'the bag (ros2 bag convert) or give time windows')
            msg = store.deserialize_cdr(raw, connection.msgtype)
            yield _stamp(msg, timestamp), msg


def read_joint_states(bag: str | Path, topic: str, joint_names: list[str],
                      typestore=None) -> Recording:
    """The task's joints of every JointState on `topic`, sorted by stamp (of messages with
    the same stamp the later in the bag: psl's simulator stamps an episode's first state with
    the time the episode before ended). ValueError: the bag cannot be read, no such topic or
    not of JointState, a message without one of the joints (named), fewer than two
    messages."""
    select = JointSelection(joint_names)
    rows: dict[float, np.ndarray] = {}
    for t, msg in _messages(bag, topic, typestore, msgtypes=(JOINT_STATE,)):
        try:
            rows[t] = select.pick(list(msg.name), list(msg.position))
        except ValueError as exc:
            raise ValueError(f'{bag}, {topic} at {t:.3f} s: {exc}') from None
    if len(rows) < 2:
        raise ValueError(f'{bag}: {len(rows)} joint states on {topic}, a demonstration needs '
                         'more')
    times = np.array(sorted(rows))
    return Recording(t=times, q=np.array([rows[t] for t in times]))


@dataclasses.dataclass(frozen=True)
class Announcement:
    """One message of a tau topic: its time t [s] (a psl_msgs/TaskInstance's stamp, else the
    bag's receive time) and tau; of a psl_msgs/TaskInstance also the episode it announces:
    its task, its length [s] (num_steps control periods; None: a std_msgs/Float64MultiArray,
    no episode), whether psl stamped it (on the robot's clock) and whether it homes the arm."""

    t: float
    tau: np.ndarray
    task: str = ''
    length: float | None = None
    stamped: bool = False
    homing: bool = False


def read_announcements(bag: str | Path, topic: str, typestore=None) -> list[Announcement]:
    """Every message on `topic` (psl_msgs/TaskInstance or std_msgs/Float64MultiArray), in the
    bag's order; ValueError for a topic of another type."""
    out = []
    for t, msg in _messages(bag, topic, typestore):
        if hasattr(msg, 'tau'):
            stamp = msg.stamp
            out.append(Announcement(t, np.asarray(msg.tau, dtype=float), str(msg.task),
                                    msg.num_steps * msg.control_period,
                                    stamp.sec != 0 or stamp.nanosec != 0,
                                    bool(getattr(msg, 'homing', False))))
        elif hasattr(msg, 'data'):
            out.append(Announcement(t, np.asarray(msg.data, dtype=float)))
        else:
            raise ValueError(f'{bag}, {topic}: {type(msg).__name__} carries no tau (a '
                             'psl_msgs/TaskInstance or a std_msgs/Float64MultiArray is needed)')
    return out


def read_instances(bag: str | Path, topic: str, typestore=None) -> list[tuple[float, np.ndarray]]:
    """(seconds, tau) of each task instance on `topic`: psl_msgs/TaskInstance (the episode's
    stamp; homing episodes skipped) or std_msgs/Float64MultiArray (its data; the bag's
    receive time)."""
    return [(a.t, a.tau) for a in read_announcements(bag, topic, typestore) if not a.homing]


def announces_episodes(announcements: list[Announcement]) -> bool:
    """Whether a tau topic holds psl's episodes (a bag of rollouts through the graph): each of
    its messages a psl_msgs/TaskInstance stamped with its episode's first state and carrying
    the episode's length, as psl's executor announces them (not a perception node's
    std_msgs/Float64MultiArray, nor a TaskInstance published by hand without them)."""
    return bool(announcements) and all(a.stamped and a.length is not None and a.length > 0
                                       for a in announcements)


def episodes(task: TaskDefinition, announcements: list[Announcement], recording: Recording,
             velocity_threshold: float = VELOCITY_THRESHOLD, min_duration: float = MIN_DURATION
             ) -> tuple[list[tuple[int, int]], list[np.ndarray], list[tuple[float, str]]]:
    """The demonstrations of a recording of episodes (rollouts through psl's graph): the
    movement of each episode announced (from its stamp for the instance's duration, without
    the settling) and its tau; and notes (time, what) on what is none: an announced homing
    episode, an episode of another task, one superseded by the next announcement before its
    movement ended (a goal that came late, sent again), one not wholly in the recording (the
    latched announcement of an episode before the recording began, one it did not see end);
    and a motion of the arm (`rest_to_rest`'s, over ``min_duration``) in no announced
    episode (an announcement missing from the bag, the arm moved by other means).
    ValueError when the announcements carry no episodes (`announces_episodes`)."""
    if not announces_episodes(announcements):
        raise ValueError('episodes need psl_msgs/TaskInstance messages as psl announces them '
                         '(their stamp and length)')
    ours = {task.name, task_id(task)}
    t = recording.t
    spans, taus, notes = [], [], []

    def skip(a: Announcement, why: str) -> None:
        notes.append((a.t, f'episode announced at {a.t:.3f} s: no demonstration ({why})'))
    for k, a in enumerate(announcements):
        if a.homing:
            skip(a, 'a homing episode, the arm driven to the start posture')
            continue
        if a.task not in ours:
            skip(a, f'an episode of the task {a.task!r}')
            continue
        end = a.t + min(a.length, task.duration_of(a.tau))
        later = [b.t for b in announcements[k + 1:] if a.t - 1e-9 < b.t < end - 1e-9]
        if later:
            skip(a, f'superseded by the episode announced at {later[0]:.3f} s')
        elif a.t < t[0] - 1e-9 or end > t[-1] + 1e-9:
            skip(a, f'not wholly in the recording, [{t[0]:.3f}, {t[-1]:.3f}] s: announced '
                 'before it began, or it ended first')
        else:
            try:
                spans.extend(windows(recording, [(a.t - 1e-9, end + 1e-9)]))
            except ValueError as exc:       # states lost in the recording
                skip(a, str(exc))
                continue
            taus.append(a.tau)
    # what the arm did outside every episode announced (the speed's window at either end)
    outside = moving(recording, velocity_threshold)
    for a in announcements:
        outside &= ~((t >= a.t - VELOCITY_WINDOW) & (t <= a.t + a.length + VELOCITY_WINDOW))
    for start, stop in _motions(t, outside):
        if t[stop - 1] - t[start] >= min_duration:
            notes.append((float(t[start]), f'motion [{t[start]:.3f}, {t[stop - 1]:.3f}] s in '
                          'no episode announced (its announcement is not in the bag, or the '
                          'arm was moved otherwise): no demonstration'))
    return spans, taus, sorted(notes, key=lambda note: note[0])


def moving(recording: Recording, velocity_threshold: float = VELOCITY_THRESHOLD
           ) -> np.ndarray:
    """Whether the arm moves at each sample, (N,) bool: its largest joint speed above
    velocity_threshold, the speed a difference over VELOCITY_WINDOW centred on the sample
    (encoder noise of sigma adds about sigma sqrt(2) / VELOCITY_WINDOW: 0.03 rad/s at
    1 mrad)."""
    t, q = recording.t, recording.q
    before = np.searchsorted(t, t - 0.5 * VELOCITY_WINDOW)
    after = np.minimum(np.searchsorted(t, t + 0.5 * VELOCITY_WINDOW, side='right') - 1,
                       len(t) - 1)
    span = np.maximum(t[after] - t[before], 1e-12)
    return np.abs(q[after] - q[before]).max(axis=1) / span > velocity_threshold


def _motions(t: np.ndarray, mask: np.ndarray) -> list[list[int]]:
    """[start, stop) index pairs of the runs of True in mask, a pause shorter than MIN_REST
    joining its neighbours."""
    merged: list[list[int]] = []
    for start, stop in _runs(mask):
        if merged and t[start] - t[merged[-1][1] - 1] < MIN_REST:
            merged[-1][1] = stop
        else:
            merged.append([start, stop])
    return merged


def rest_to_rest(recording: Recording, velocity_threshold: float = VELOCITY_THRESHOLD,
                 min_duration: float = MIN_DURATION) -> list[tuple[int, int]]:
    """The demonstrations of a recording: index spans [i, j] (inclusive) from the last sample
    at rest before a motion to the first at rest after it, kept if they last at least
    min_duration. The arm moves while its largest joint speed is above velocity_threshold
    (`moving`); a pause shorter than MIN_REST is part of the motion. A motion still going
    at the end of the recording is not kept."""
    if not (velocity_threshold > 0 and min_duration >= 0):
        raise ValueError(f'velocity_threshold must be > 0 and min_duration >= 0, got '
                         f'{velocity_threshold!r}, {min_duration!r}')
    t = recording.t
    merged = _motions(t, moving(recording, velocity_threshold))
    spans = []
    for start, stop in merged:
        if stop >= len(t):
            break                              # still moving when the recording ends
        first, last = max(start - 1, 0), stop
        if t[last] - t[first] >= min_duration:
            spans.append((first, last))
    return spans


def split_returns(task: TaskDefinition, recording: Recording, spans: list[tuple[int, int]],
                  start_tolerance: float = START_TOLERANCE
                  ) -> tuple[list[tuple[int, int]], list[tuple[int, int]]]:
    """(demonstrations, returns) of rest-to-rest spans: a return starts off the task's start
    posture and ends at it (within start_tolerance): the arm brought back between two
    demonstrations, which is no demonstration. Every other motion is one (`teach_one` refuses
    one that does not start at the start posture, with the reason)."""
    start = np.asarray(task.start_posture)

    def at(k: int) -> bool:
        return bool(np.abs(recording.q[k] - start).max() <= start_tolerance)
    back = [not at(i) and at(j) for i, j in spans]
    return ([s for s, r in zip(spans, back) if not r], [s for s, r in zip(spans, back) if r])


def motion_start(recording: Recording, span: tuple[int, int]) -> float:
    """When the arm starts to move in a span of `rest_to_rest`: its first moving sample plus
    half the speed window (a difference centred on a sample sees a motion half a window
    before it begins). The span's first sample, the last at rest, may lie before an
    instance psl announced for the very time its episode starts."""
    i, j = span
    return float(recording.t[min(i + 1, j)]) + 0.5 * VELOCITY_WINDOW


def _runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """(start, stop) index pairs of the runs of True in mask (stop exclusive)."""
    edges = np.diff(np.concatenate([[0], mask.astype(np.int8), [0]]))
    return list(zip(np.flatnonzero(edges == 1).tolist(), np.flatnonzero(edges == -1).tolist()))


def windows(recording: Recording, spans: list[tuple[float, float]]) -> list[tuple[int, int]]:
    """Index spans of given time windows [a, b] s (the recording's clock); ValueError for a
    window with fewer than two samples."""
    out = []
    for a, b in spans:
        inside = np.flatnonzero((recording.t >= a) & (recording.t <= b))
        if len(inside) < 2:
            raise ValueError(f'the window [{a:g}, {b:g}] s holds {len(inside)} joint states '
                             f'(the recording spans [{recording.t[0]:g}, {recording.t[-1]:g}] s)')
        out.append((int(inside[0]), int(inside[-1])))
    return out


def taus_from_topic(announcements: list[Announcement], recording: Recording,
                    spans: list[tuple[int, int]], motions: bool = True) -> list:
    """Each span's instance from a tau topic's `announcements` (`read_announcements`, homing
    episodes skipped; `instance_at`): the last announced before the arm starts to move
    (`motion_start`: spans of `rest_to_rest`), or with ``motions=False`` before the span
    starts (time windows given)."""
    instances = [(a.t, a.tau) for a in announcements if not a.homing]
    return [instance_at(instances, motion_start(recording, span) if motions
                        else float(recording.t[span[0]])) for span in spans]


def instance_at(instances: list[tuple[float, np.ndarray]], start: float) -> np.ndarray | None:
    """The tau of the last instance announced at or before `start` (None: none was)."""
    before = [tau for t, tau in instances if t <= start + 1e-9]
    return before[-1] if before else None


def teach_one(task: TaskDefinition, policy: TaskPolicy, t: np.ndarray, q: np.ndarray,
              tau, start_tolerance: float = START_TOLERANCE,
              fit_tolerance: float = FIT_TOLERANCE, safety: SafetyCheck | None = None
              ) -> Outcome:
    """One demonstration (q (T, n) at times t (T,)) on instance tau: its sample, or why it is
    refused (module docstring, 4). ``safety``: the task's check, made once by a caller that
    teaches many (default: made here)."""
    span = float(t[0]), float(t[-1])

    def refuse(reason: str, error: float = float('nan')) -> Outcome:
        return Outcome(*span, tau=None if tau is None else np.asarray(tau, dtype=float),
                       theta=None, fit_error=error, reason=reason)
    if tau is None:
        return refuse('no task instance for it (give tau, or a topic that announced one '
                      'before it started)')
    try:
        tau = task.validate_tau(np.asarray(tau, dtype=float))
    except (TaskError, ValueError) as exc:
        return refuse(f'its task instance: {exc}')
    off = np.abs(q[0] - np.asarray(task.start_posture)).max()
    if off > start_tolerance:
        return refuse(f'it starts {off:.3f} rad from the start posture (tolerance '
                      f'{start_tolerance:g})')
    try:
        theta = policy.fit_demonstration(t, q)
        reference = policy.reference(theta, tau)
    except ValueError as exc:
        return refuse(f'it cannot be fitted: {exc}')
    # the fitted movement against the demonstration, on the demonstration's mapped times
    duration = task.duration_of(tau)
    mapped = (t - t[0]) * (duration / (t[-1] - t[0]))
    moved = np.column_stack([np.interp(mapped, reference.t, reference.q[:, j])
                             for j in range(task.n_joints)])
    error = float(np.abs(moved - q).max())
    if error > fit_tolerance:
        return refuse(f'the fitted movement stays {error:.3f} rad from it (tolerance '
                      f'{fit_tolerance:g}: a goal the policy cannot learn, or a motion its '
                      f'{task.policy.n_basis} basis functions cannot follow)', error)
    verdict = (safety or SafetyCheck(ArmModel(task))).check(tau, reference.q, reference.qd,
                                                          reference.u_ffwd)
    if not verdict.safe:
        return refuse(f'the safety check refuses its movement: {verdict.reason}', error)
    return Outcome(*span, tau=tau, theta=theta, fit_error=error)


def teach(task: TaskDefinition, recording: Recording, spans: list[tuple[int, int]],
          taus: list, memory, start_tolerance: float = START_TOLERANCE,
          fit_tolerance: float = FIT_TOLERANCE) -> list[Outcome]:
    """Each demonstration (index span of the recording) on its instance (taus, one per span,
    None: unknown): `teach_one`; the accepted samples are added to the task's skill in
    `memory` (a `SkillMemory`, created there if absent), the refused ones are not."""
    if len(taus) != len(spans):
        raise ValueError(f'{len(spans)} demonstrations but {len(taus)} task instances')
    policy, safety = TaskPolicy(task), SafetyCheck(ArmModel(task))
    outcomes = [teach_one(task, policy, recording.t[i:j + 1], recording.q[i:j + 1], tau,
                          start_tolerance, fit_tolerance, safety)
                for (i, j), tau in zip(spans, taus)]
    if task.name not in memory.skills:
        memory.create(task.name, task.tau_low, task.tau_high, policy.default_theta)
    for outcome in outcomes:
        if outcome.accepted:
            memory.add(task.name, outcome.tau, outcome.theta)
    return outcomes
