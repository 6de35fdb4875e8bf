"""``psl teach``: skill samples from kinesthetic demonstrations recorded in a bag
(`psl_optimizer.teaching`): the bag's joint states cut into demonstrations, each with its task
instance, fitted, checked, and the accepted ones added to a skill memory file that ``psl learn
--continue-from`` starts from."""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from psl_cli import options


def add_arguments(p: argparse.ArgumentParser) -> None:
    from psl_optimizer import teaching

    options.add_task(p)
    p.add_argument('bag', help='a rosbag2 folder (MCAP or sqlite3: psl record, ros2 bag record)')
    p.add_argument('--topic', default='/joint_states',
                   help='the sensor_msgs/JointState topic (default /joint_states)')
    source = p.add_mutually_exclusive_group(required=True)
    source.add_argument('--tau', nargs='+', type=float, action='append', metavar='X',
                        help='the task instance of the next demonstration (once per '
                        'demonstration, in order)')
    source.add_argument('--tau-file', metavar='FILE',
                        help='the task instances, one line of numbers per demonstration')
    source.add_argument('--tau-topic', metavar='TOPIC',
                        help='a topic of the bag announcing the instances: psl_msgs/TaskInstance '
                        '(e.g. /task_instance: psl\'s episodes, each taken with its tau) or '
                        'std_msgs/Float64MultiArray (a demonstration takes the last one '
                        'announced before it starts)')
    cut = p.add_mutually_exclusive_group()
    cut.add_argument('--window', nargs=2, type=float, action='append', metavar=('A', 'B'),
                     help='a demonstration is the span [A, B] s of the recording (the robot\'s '
                     'clock; repeatable); default: the episodes psl announced on --tau-topic, '
                     'else rest-to-rest segmentation')
    cut.add_argument('--episodes', action='store_true',
                     help='the demonstrations are the episodes --tau-topic announced '
                     '(psl_msgs/TaskInstance: rollouts recorded from psl\'s graph), each with '
                     'its tau; the default when that topic announces them, this makes it an '
                     'error when it does not')
    p.add_argument('--velocity-threshold', type=options.positive_float,
                   default=teaching.VELOCITY_THRESHOLD, metavar='RAD_S',
                   help='the arm rests while no joint moves faster (default %(default)g)')
    p.add_argument('--min-duration', type=float, default=teaching.MIN_DURATION, metavar='S',
                   help='a shorter motion is no demonstration (default %(default)g s)')
    p.add_argument('--start-tolerance', type=options.positive_float,
                   default=teaching.START_TOLERANCE, metavar='RAD',
                   help='how far from the start posture a demonstration may start (default '
                   '%(default)g rad)')
    p.add_argument('--fit-tolerance', type=options.positive_float,
                   default=teaching.FIT_TOLERANCE, metavar='RAD',
                   help='how far the fitted movement may stay from the demonstration (default '
                   '%(default)g rad)')
    p.add_argument('--into', metavar='FILE',
                   help='add to the skill of this memory file (default: a new memory)')
    p.add_argument('-o', '--out', required=True, metavar='FILE',
                   help='the memory file to write (it may be --into\'s)')


def _taus(args, spans, recording, announcements: list) -> list:
    from psl_optimizer import teaching

    if args.tau_topic:
        return teaching.taus_from_topic(announcements, recording, spans,
                                        motions=not args.window)
    if args.tau_file:
        from psl_cli.vectors import load_rows
        taus = load_rows(args.tau_file)
    else:
        taus = [np.array(tau) for tau in args.tau]
    if len(taus) != len(spans):
        raise ValueError(f'{len(spans)} demonstrations in the bag but {len(taus)} task '
                         'instances given')
    return taus


def run(args) -> int:
    from psl_memory.skill_memory import SkillMemory
    from psl_optimizer import teaching
    from psl_optimizer.learning import LearnSettings
    from psl_task.arm_model import joint_names_of
    from psl_task.task import load_task

    try:
        task = load_task(args.task)
        bag = Path(args.bag)
        recording = teaching.read_joint_states(bag, args.topic, joint_names_of(task))
        returns, notes = [], []
        by_episodes = args.episodes
        if by_episodes and not args.tau_topic:
            raise ValueError('--episodes needs --tau-topic (the topic announcing them)')
        announcements = []          # the tau topic's messages, read once
        if args.tau_topic:
            from psl_ros.bag_recorder import make_typestore
            announcements = teaching.read_announcements(bag, args.tau_topic, make_typestore())
        if args.tau_topic and not args.window:
            if not by_episodes and teaching.announces_episodes(announcements):
                by_episodes = True
                print(f'psl teach: {args.tau_topic} announces psl\'s episodes '
                      '(psl_msgs/TaskInstance): each episode\'s movement is a demonstration '
                      'with its tau, as with --episodes (--window A B cuts otherwise)',
                      file=sys.stderr)
        if by_episodes:
            spans, taus, notes = teaching.episodes(task, announcements, recording,
                                                   args.velocity_threshold, args.min_duration)
            if not spans:
                raise ValueError(f'no episode of the task in {bag} announced on '
                                 f'{args.tau_topic}: ' + '; '.join(note for _, note in notes))
        elif args.window:
            spans = teaching.windows(recording, args.window)
        else:
            spans, returns = teaching.split_returns(task, recording, teaching.rest_to_rest(
                recording, args.velocity_threshold, args.min_duration), args.start_tolerance)
        if not spans:
            raise ValueError(f'no demonstration in {bag} (no motion from rest to rest above '
                             f'{args.velocity_threshold:g} rad/s for {args.min_duration:g} s '
                             f'that is not a return to the start posture; {len(returns)} '
                             'returns)')
        if not by_episodes:
            taus = _taus(args, spans, recording, announcements)
        memory = (SkillMemory.read(args.into) if args.into
                  else SkillMemory(LearnSettings().skill))
        outcomes = teaching.teach(task, recording, spans, taus, memory, args.start_tolerance,
                                  args.fit_tolerance)
    except (ValueError, OSError) as exc:        # TaskError, a bag or file that is not one
        return options.fail('psl teach', exc, 2)
    for _, note in notes:
        print(note)
    for i, j in returns:
        print(f'motion [{recording.t[i]:.3f}, {recording.t[j]:.3f}] s: the arm brought back '
              'to the start posture, no demonstration')
    for k, outcome in enumerate(outcomes, 1):
        tau = ('?' if outcome.tau is None
               else ' '.join(f'{x:g}' for x in np.asarray(outcome.tau)))
        head = (f'demonstration {k} [{outcome.start:.3f}, {outcome.end:.3f}] s, tau {tau}: ')
        print(head + (f'accepted (fitted within {outcome.fit_error:.4f} rad)' if outcome.accepted
                      else f'refused: {outcome.reason}'))
    accepted = sum(o.accepted for o in outcomes)
    if not accepted:
        return options.fail('psl teach', 'every demonstration was refused: nothing written', 1)
    memory.save(args.out)
    print(f'{accepted} of {len(outcomes)} demonstrations added to the skill {task.name!r} in '
          f'{args.out} ({memory.get(task.name).num_samples} samples); continue with: psl learn '
          f'--task {args.task} --continue-from {args.out} --continuation samples')
    return 0
