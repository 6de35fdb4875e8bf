"""psl teach's library (`psl_optimizer.teaching`): a bag of joint states written here (rosbags,
MCAP, as psl record writes it; the robot's joint order, an extra joint, noise) with guided
demonstrations (the policy's own movements for known instances, so the right theta is known),
a nudge, and demonstrations that must be refused; against the segmentation's closed form,
the policy's reference and the skill memory's samples."""
import numpy as np
import pytest

from psl_controller.policy import TaskPolicy, policy_for
from psl_memory.skill_memory import SkillMemory
from psl_optimizer import teaching
from psl_optimizer.learning import LearnSettings
from psl_task.arm_model import joint_names_of
from psl_task.task import load_task

TASK = 'planar_10dof_reach'
NOISE = 2e-4                # rad, the encoders' noise
REST = 0.5                  # s at rest before and after each demonstration
TOL_TAUGHT = 0.05           # rad, a taught movement against the demonstrated one (the
                            # segment's rest at either end is mapped onto the movement)


def write_bag(path, stamps, rows, names, instances=()):
    """A rosbag2 (MCAP) with sensor_msgs/JointState on /joint_states (names, positions
    rows (N, m), header stamps [s]) and std_msgs/Float64MultiArray on /perception at the
    given (seconds, tau)."""
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore
    store = get_typestore(Stores.ROS2_JAZZY)
    JointState = store.types['sensor_msgs/msg/JointState']
    Header = store.types['std_msgs/msg/Header']
    Time = store.types['builtin_interfaces/msg/Time']
    Array = store.types['std_msgs/msg/Float64MultiArray']
    Layout = store.types['std_msgs/msg/MultiArrayLayout']
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        joints = writer.add_connection('/joint_states', JointState.__msgtype__, typestore=store)
        seen = writer.add_connection('/perception', Array.__msgtype__, typestore=store)
        events = [(t, 'tau', tau) for t, tau in instances]
        events += [(t, 'q', row) for t, row in zip(stamps, rows)]
        for t, kind, value in sorted(events, key=lambda e: (e[0], e[1] == 'q')):
            ns = int(round(t * 1e9))
            if kind == 'tau':
                msg = Array(layout=Layout(dim=[], data_offset=0),
                            data=np.asarray(value, dtype=float))
                writer.write(seen, ns, store.serialize_cdr(msg, Array.__msgtype__))
            else:
                msg = JointState(header=Header(stamp=Time(sec=ns // 10**9,
                                                          nanosec=ns % 10**9), frame_id=''),
                                 name=names, position=np.asarray(value, dtype=float),
                                 velocity=np.zeros(0), effort=np.zeros(0))
                writer.write(joints, ns, store.serialize_cdr(msg, JointState.__msgtype__))


@pytest.fixture(scope='module')
def task():
    return load_task(TASK)


def shown_thetas(task, taus, rng):
    """A demonstrator's thetas, one per instance: the default's DMP weights and goal each
    moved at random, so far that each movement stays more than 4 TOL_TAUGHT from the
    default's somewhere (a fit that returned the default theta, or its weights with the
    demonstration's end as the goal, would not reproduce them)."""
    policy = policy_for(task)
    default = policy.reference(policy.default_theta).q
    weights = slice(0, policy.goal.start)
    scale = max(1.0, float(np.abs(policy.default_theta[weights]).max()))
    thetas = []
    for tau in taus:
        theta = policy.default_theta.copy()
        theta[weights] += rng.normal(0.0, 0.1 * scale, weights.stop)
        theta[policy.goal] += rng.normal(0.0, 0.1, policy.goal.stop - policy.goal.start)
        assert np.abs(policy.reference(theta, tau).q - default).max() > 4 * TOL_TAUGHT
        thetas.append(theta)
    return thetas


def assert_taught(task, taught_thetas, taus, shown):
    """Each taught theta's movement reproduces the shown one within TOL_TAUGHT, which lies
    more than 4 TOL_TAUGHT from the default's."""
    policy = policy_for(task)
    default = policy.reference(policy.default_theta).q
    for theta, tau, truth in zip(taught_thetas, taus, shown):
        mine, seen = policy.reference(theta, tau).q, policy.reference(truth, tau).q
        assert np.abs(mine - seen).max() < TOL_TAUGHT
        assert np.abs(mine - default).max() > 4 * TOL_TAUGHT


def guided(task, thetas, taus, offsets=None, rng=None):
    """Joint states (t, q) of demonstrations: each theta's reference (its motion, without
    the settling) framed by REST s at rest, one after the other; offsets (per demonstration,
    (n,) added to every posture) make one start elsewhere."""
    policy = policy_for(task)
    dt = task.control_period
    chunks, t0 = [], 0.0
    for k, (theta, tau) in enumerate(zip(thetas, taus)):
        q = policy.reference(theta, tau).q[:int(round(task.duration / dt)) + 1]
        if offsets is not None:
            q = q + offsets[k]
        rest = int(round(REST / dt))
        q = np.vstack([np.repeat(q[:1], rest, axis=0), q, np.repeat(q[-1:], rest, axis=0)])
        chunks.append((t0 + np.arange(len(q)) * dt, q))
        t0 += len(q) * dt + 1.0
    t = np.concatenate([c[0] for c in chunks])
    q = np.vstack([c[1] for c in chunks])
    if rng is not None:
        q = q + rng.normal(0.0, NOISE, q.shape)
    return t, q


def test_rest_to_rest_finds_the_motions_and_drops_a_nudge():
    """Three motions of 1 s (minimum jerk, out and back) between rests, a 0.2 s nudge: three
    spans, each from the rest before its motion to the rest after it (within the speed's
    50 ms window)."""
    dt = 0.002
    t = np.arange(0, 8.0, dt)
    q = np.zeros((len(t), 2))
    for begin, sign in ((1.0, 1.0), (3.0, -1.0), (6.0, 1.0)):
        s = np.clip(t - begin, 0.0, 1.0)
        q[:, 0] += sign * (10 * s**3 - 15 * s**4 + 6 * s**5)
    nudge = (t > 5.0) & (t < 5.2)
    q[nudge, 1] = 0.01 * np.sin(np.pi * (t[nudge] - 5.0) / 0.2)
    spans = teaching.rest_to_rest(teaching.Recording(t=t, q=q), 0.05, 0.5)
    assert len(spans) == 3
    for (i, j), begin in zip(spans, (1.0, 3.0, 6.0)):
        assert begin - 0.03 <= t[i] <= begin + 0.1 and begin + 0.9 <= t[j] <= begin + 1.03


def test_a_bag_of_guided_demonstrations_becomes_the_skills_samples(task, tmp_path):
    """Three demonstrations of known thetas on known instances (tau from a perception topic,
    the robot's own joint order plus a gripper joint, encoder noise): each is accepted, its
    theta's movement reproduces it, and the skill holds exactly these samples; a fourth that
    starts 0.2 rad off the start posture is refused with the reason and adds nothing."""
    policy = TaskPolicy(task)
    rng = np.random.default_rng(0)
    taus = [np.array([0.5, 0.2]), np.array([0.62, 0.35]), np.array([0.45, 0.1]),
            np.array([0.55, 0.3])]
    thetas = shown_thetas(task, taus, rng)
    offsets = [np.zeros(task.n_joints)] * 3 + [np.full(task.n_joints, 0.02)]
    offsets[3][0] = 0.2
    t, q = guided(task, thetas, taus, offsets, rng)
    names = joint_names_of(task)
    robot_order = names[::-1] + ['gripper']
    rows = np.column_stack([q[:, ::-1], np.zeros(len(q))])
    starts = []
    recording_t = t
    bag = tmp_path / 'guided'
    spans_expected = teaching.rest_to_rest(teaching.Recording(t=t, q=q))
    for i, _ in spans_expected:
        starts.append(recording_t[i] - 0.3)
    write_bag(bag, t + 100.0, rows, robot_order,
              [(s + 100.0, tau) for s, tau in zip(starts, taus)])

    recording = teaching.read_joint_states(bag, '/joint_states', names)
    np.testing.assert_array_equal(recording.q, q)
    spans = teaching.rest_to_rest(recording)
    assert len(spans) == 4
    instances = teaching.read_instances(bag, '/perception')
    found = [teaching.instance_at(instances, recording.t[i]) for i, _ in spans]
    for got, tau in zip(found, taus):
        np.testing.assert_array_equal(got, tau)
    memory = SkillMemory(LearnSettings().skill)
    outcomes = teaching.teach(task, recording, spans, found, memory)
    assert [o.accepted for o in outcomes] == [True, True, True, False]
    assert 'starts 0.200 rad from the start posture' in outcomes[3].reason
    skill = memory.get(task.name)
    assert skill.num_samples == 3
    for outcome, tau, theta in zip(outcomes[:3], taus, thetas):
        # the segment holds a few ms of rest at either end, mapped onto the movement's
        # duration with it: the fit is that much slower at the ends
        assert outcome.fit_error < TOL_TAUGHT
        np.testing.assert_array_equal(outcome.tau, tau)
        # the learned goal is where the demonstration ends (the DMP has nearly converged there
        # at the end of its duration), the movement the demonstrated one
        np.testing.assert_allclose(outcome.theta[policy.goal], theta[policy.goal],
                                   atol=TOL_TAUGHT)
    assert_taught(task, [o.theta for o in outcomes[:3]], taus[:3], thetas[:3])
    np.testing.assert_array_equal(skill.taus, np.array(taus[:3]))


def test_a_demonstration_the_policy_cannot_follow_is_refused(task):
    """reach_over_obstacle's goal posture is fixed (no learned goal): a demonstration that
    ends elsewhere cannot be fitted; so is an instance outside the task's range."""
    task = load_task('reach_over_obstacle')
    policy = TaskPolicy(task)
    reference = policy.reference(policy.default_theta)
    steps = int(round(task.duration / task.control_period)) + 1
    q = reference.q[:steps] + np.linspace(0.0, 0.3, steps)[:, None]      # ends 0.3 rad off
    t = reference.t[:steps]
    far = teaching.teach_one(task, policy, t, q, task.tau_default)
    assert not far.accepted and 'the fitted movement stays' in far.reason
    good = teaching.teach_one(task, policy, t, reference.q[:steps], task.tau_default)
    assert good.accepted and good.fit_error < 5e-3
    outside = teaching.teach_one(task, policy, t, reference.q[:steps], task.tau_high + 1.0)
    assert not outside.accepted and 'its task instance' in outside.reason
    unknown = teaching.teach_one(task, policy, t, reference.q[:steps], None)
    assert not unknown.accepted and 'no task instance' in unknown.reason


def test_bags_that_are_not_demonstrations_get_clear_errors(task, tmp_path):
    names = joint_names_of(task)
    bag = tmp_path / 'short'
    write_bag(bag, [0.0, 0.01], np.zeros((2, len(names) - 1)), names[:-1])
    with pytest.raises(ValueError, match=names[-1]):
        teaching.read_joint_states(bag, '/joint_states', names)
    with pytest.raises(ValueError, match="no topic '/other'"):
        teaching.read_joint_states(bag, '/other', names)


def test_psl_teach_writes_a_memory_that_psl_learn_continues(task, tmp_path, capsys):
    """The command end to end: a bag of two guided demonstrations and one that starts off
    the start posture, instances from the perception topic -> a memory file with the two
    samples (the refused one named with its reason) -> psl learn --continue-from it."""
    from psl_cli.main import main
    policy = TaskPolicy(task)
    taus = [np.array([0.5, 0.2]), np.array([0.6, 0.3]), np.array([0.45, 0.15])]
    offsets = [np.zeros(task.n_joints), np.zeros(task.n_joints),
               np.full(task.n_joints, 0.15)]
    rng = np.random.default_rng(1)
    shown = shown_thetas(task, taus, rng)
    t, q = guided(task, shown, taus, offsets, rng)
    spans = teaching.rest_to_rest(teaching.Recording(t=t, q=q))
    bag = tmp_path / 'taught'
    write_bag(bag, t, q, joint_names_of(task), [(t[i] - 0.2, tau) for (i, _), tau in
                                                zip(spans, taus)])
    memory = tmp_path / 'taught.npz'
    assert main(['teach', '--task', TASK, str(bag), '--tau-topic', '/perception',
                 '-o', str(memory)]) == 0
    out = capsys.readouterr().out
    assert out.count('accepted') == 2 and 'refused: it starts 0.150 rad' in out
    taught = SkillMemory.read(memory).get(task.name)
    assert taught.num_samples == 2
    np.testing.assert_array_equal(taught.taus, np.array(taus[:2]))
    assert_taught(task, taught.thetas, taus[:2], shown[:2])
    run = tmp_path / 'run'
    assert main(['learn', '--task', TASK, '--tasks', '2', '--test-tasks', '2',
                 '--continue-from', str(memory), '--continuation', 'samples',
                 '--out', str(run)]) == 0
    # the session went on from the taught samples: its skill holds them, then its own
    learned = SkillMemory.read(run / 'memory.npz').get(task.name)
    np.testing.assert_array_equal(learned.taus[:2], taught.taus)
    np.testing.assert_array_equal(learned.thetas[:2], taught.thetas)
    assert learned.num_samples > 2
    # a bag in which nothing is accepted writes nothing and says so
    assert main(['teach', '--task', TASK, str(bag), '--tau', '0.5', '0.2', '--tau', '0.6',
                 '0.3', '--tau', '3.0', '3.0', '--start-tolerance', '1e-6',
                 '-o', str(tmp_path / 'none.npz')]) == 1
    assert not (tmp_path / 'none.npz').exists()
    assert 'every demonstration was refused' in capsys.readouterr().err


@pytest.mark.parametrize('name', ['reach_over_obstacle', 'planar_10dof_reach',
                                  'point_reach_3d', 'pose_reach_3d'])
def test_the_yamls_demonstration_taught_at_another_speed_is_the_default_theta(name):
    """TaskPolicy.fit_demonstration maps the demonstration's time onto the movement's: the
    YAML's own demonstration, given 1.7 times slower, gives the default theta (fitted to it
    at the task's duration) within the fit's rounding; the policy itself is not changed."""
    from psl_controller.dmp import demonstration_from_waypoints
    task = load_task(name)
    policy = TaskPolicy(task)
    before = policy.reference(policy.default_theta).q
    t, q = demonstration_from_waypoints(task.demo_times, task.demo_positions,
                                        task.control_period)
    theta = policy.fit_demonstration(1.7 * t, q)
    scale = max(1.0, np.abs(policy.default_theta).max())
    np.testing.assert_allclose(theta, policy.default_theta, rtol=0, atol=1e-9 * scale)
    np.testing.assert_array_equal(policy.reference(policy.default_theta).q, before)


def with_returns(task, thetas, taus):
    """A person's session: for each instance REST s at rest at the start posture, the
    policy's movement (without the settling), REST s at rest, the arm brought back to the
    start posture (1 s, minimum jerk); (t, q) and the time each movement begins."""
    policy = policy_for(task)
    dt = task.control_period
    start = np.asarray(task.start_posture)
    s = np.linspace(0.0, 1.0, int(round(1.0 / dt)) + 1)[1:]
    blend = (10 * s**3 - 15 * s**4 + 6 * s**5)[:, None]
    rest = int(round(REST / dt))
    pieces, begins, count = [], [], 0
    for theta, tau in zip(thetas, taus):
        moved = policy.reference(theta, tau).q[:int(round(task.duration / dt)) + 1]
        begins.append((count + rest) * dt)
        piece = np.vstack([np.repeat(start[None], rest, axis=0), moved,
                           np.repeat(moved[-1:], rest, axis=0),
                           moved[-1] + blend * (start - moved[-1])])
        pieces.append(piece)
        count += len(piece)
    pieces.append(np.repeat(start[None], rest, axis=0))
    q = np.vstack(pieces)
    return np.arange(len(q)) * dt, q, begins


def test_returns_to_the_start_are_no_demonstrations_and_take_no_tau(task, tmp_path, capsys):
    """A person's session: demonstration, the arm brought back, demonstration, ... The
    returns are said and skipped (no tau consumed, nothing refused); taus from a file pair
    with the demonstrations in order; instances announced exactly when a motion begins (as
    psl stamps an episode) are found for it (`motion_start`: the speed over a centred window
    may cross the threshold before the motion begins, the span's first sample then with
    it)."""
    from psl_cli.main import main
    policy = TaskPolicy(task)
    taus = [np.array([0.5, 0.2]), np.array([0.6, 0.3]), np.array([0.45, 0.15])]
    demonstrated = shown_thetas(task, taus, np.random.default_rng(2))
    t, q, begins = with_returns(task, demonstrated, taus)
    recording = teaching.Recording(t=t, q=q)
    shown, returns = teaching.split_returns(task, recording, teaching.rest_to_rest(recording))
    assert len(shown) == 3 and len(returns) == 3
    for span, begin in zip(shown, begins):     # not before the movement, and close to it
        assert begin <= teaching.motion_start(recording, span) <= begin + 0.1
    # instances stamped at the motions' very beginnings
    bag = tmp_path / 'session'
    write_bag(bag, t, q, joint_names_of(task), list(zip(begins, taus)))
    found = [teaching.instance_at(teaching.read_instances(bag, '/perception'),
                                  teaching.motion_start(recording, span)) for span in shown]
    for got, tau in zip(found, taus):
        np.testing.assert_array_equal(got, tau)
    tau_file = tmp_path / 'taus.txt'
    tau_file.write_text(''.join(' '.join(f'{x:g}' for x in tau) + '\n' for tau in taus))
    for given in (['--tau-file', str(tau_file)], ['--tau-topic', '/perception']):
        out_file = tmp_path / f'{given[0][2:]}.npz'
        assert main(['teach', '--task', TASK, str(bag), *given, '-o', str(out_file)]) == 0
        out = capsys.readouterr().out
        assert out.count('accepted') == 3 and 'refused' not in out, out
        assert out.count('brought back to the start posture') == 3, out
        taught = SkillMemory.read(out_file).get(task.name)
        np.testing.assert_array_equal(taught.taus, np.array(taus))
        assert_taught(task, taught.thetas, taus, demonstrated)


def rollouts(task, thetas, taus):
    """Joint states of rollouts through psl's graph with the task's teleport reset: each
    episode the policy's reference (movement and settling, num_steps + 1 states) from its
    stamp, the next one's first state (teleported to the start posture) stamped with the time
    the one before ended and kept in its place; (recording, each episode's stamp)."""
    policy = policy_for(task)
    rows, stamps = {}, []
    for k, (theta, tau) in enumerate(zip(thetas, taus)):
        stamp = k * task.num_steps_of(tau) * task.control_period
        stamps.append(stamp)
        reference = policy.reference(theta, tau)
        for t, q in zip(reference.t, reference.q):
            rows[round(stamp + t, 9)] = q
    t = np.array(sorted(rows))
    return teaching.Recording(t=t, q=np.array([rows[s] for s in t])), stamps


def test_a_recording_of_rollouts_is_cut_by_the_episodes_psl_announced(task):
    """psl's rollouts with teleport resets: cut from rest to rest, the teleport (a jump of
    the arm between two states) begins the next motion, which then starts at the goal of the
    episode before and is refused (through the graph the PD's settling leaves less than
    MIN_REST at rest before it, and all episodes are one motion no fit follows); the episodes
    psl announced cut them, each with its tau and without the settling. Announcements that
    are no demonstration of the recording are said: the latched one of an episode before the
    recording, a homing episode, an episode of another task, one announced again later (its
    goal came late)."""
    taus = [np.array([0.5, 0.2]), np.array([0.62, 0.35]), np.array([0.45, 0.1])]
    thetas = shown_thetas(task, taus, np.random.default_rng(3))
    recording, stamps = rollouts(task, thetas, taus)
    by_motion = teaching.rest_to_rest(recording)
    for (i, _), stamp in zip(by_motion[1:], stamps[1:]):     # the teleport begins the motion
        assert recording.t[i] < stamp
    refused = teaching.teach(task, recording, by_motion, taus[:len(by_motion)],
                             SkillMemory(LearnSettings().skill))[1:]
    assert refused and all('from the start posture' in o.reason for o in refused)
    length = task.num_steps_of(None) * task.control_period

    def episode(t, tau, **kw):
        return teaching.Announcement(t, tau, kw.pop('task', task.name), length, True, **kw)
    announced = ([episode(stamps[0] - length, taus[1])]                     # latched
                 + [episode(s, tau) for s, tau in zip(stamps[:2], taus)]
                 + [episode(stamps[2] - 0.25, taus[2]),     # its goal came late: sent again
                    episode(stamps[2], taus[2]),
                    episode(stamps[2] + length, taus[0], homing=True),
                    episode(stamps[2] + length, taus[0], task='reach_over_obstacle')])
    assert teaching.announces_episodes(announced)
    spans, found, notes = teaching.episodes(task, announced, recording)
    assert len(spans) == 3 and len(notes) == 4, notes
    said = ' | '.join(note for _, note in notes)
    for why in ('not wholly in the recording', 'a homing episode',
                "an episode of the task 'reach_over_obstacle'",
                'superseded by the episode announced'):
        assert f'no demonstration ({why}' in said
    for (i, j), stamp, tau, got in zip(spans, stamps, taus, found):
        assert recording.t[i] == pytest.approx(stamp)
        assert recording.t[j] == pytest.approx(stamp + task.duration_of(tau))
        np.testing.assert_array_equal(got, tau)
    memory = SkillMemory(LearnSettings().skill)
    outcomes = teaching.teach(task, recording, spans, found, memory)
    assert all(o.accepted for o in outcomes), [o.reason for o in outcomes]
    assert_taught(task, [o.theta for o in outcomes], taus, thetas)
    # an announcement missing from the bag (a lossy recording): its episode is no
    # demonstration, and its motion is said
    spans, found, notes = teaching.episodes(task, announced[:3] + announced[5:], recording)
    assert len(spans) == 2 and [note for _, note in notes if 'motion' in note] == [
        notes[-3][1]], notes
    assert 'in no episode announced' in notes[-3][1]
    assert stamps[2] <= notes[-3][0] <= stamps[2] + 0.1
    # a perception node's instances, and a TaskInstance published by hand (no stamp, no
    # length), announce no episodes: those bags are cut from rest to rest
    assert not teaching.announces_episodes([teaching.Announcement(1.0, taus[0])])
    assert not teaching.announces_episodes([teaching.Announcement(1.0, taus[0], task.name,
                                                                  0.0)])
    assert not teaching.announces_episodes([])
    with pytest.raises(ValueError, match='episodes need psl_msgs/TaskInstance'):
        teaching.episodes(task, [teaching.Announcement(1.0, taus[0])], recording)
