"""Record ROS 2 topics into a rosbag2 bag (MCAP storage) without rosbag2.

The ``ros2`` command line and rosbag2 are not installed here (DESIGN.md section 6), so bags are
written with the ``rosbags`` library in the layout ``ros2 bag record -s mcap`` of ROS 2 Jazzy
produces: a folder with ``metadata.yaml`` (version 9) and one ``.mcap`` file whose schemas are
the concatenated ``.msg`` definitions (``ros2msg``) with their RIHS01 type hashes, so that
``ros2 bag info/play`` on a full install and Foxglove open it.

Messages are taken as serialized CDR bytes and written unchanged, stamped with the
middleware's receive time (system clock), as ``ros2 bag record`` of Jazzy does. The
subscription QoS follows the publishers: reliable if all publishers are reliable,
transient-local if all are (so latched topics are captured), and keep-all history. The
publishers' offered QoS profiles go into the topic metadata.

Nothing is dropped silently. Taking and writing are separate threads: a `HotPath` thread
waits on the recording subscriptions alone (a fixed wait set, not an executor) and takes what
has arrived, in batches a few milliseconds apart, into an unbounded queue; a writer thread
empties the queue into the bag every 50 ms, so taking never waits on the disk (about 25 us of
CPU per message in all, DDS included, against about 200 us for an executor callback that
wrote under a lock). While the recorder falls behind, a reliable keep-all subscription keeps
what it has not taken (Fast DDS's default resource limit: 5000 samples per topic; a
keep-last subscription would overwrite its oldest samples without any notice), and beyond
that a publisher keeps in its history what the subscription has not acknowledged (the
graph's per-step topics: `psl_ros.qos.RELIABLE`, 5000 deep). A message lost all the same (a
publisher's keep-last history overwrote it, a best-effort sample did not arrive, the disk
refused it) is counted per topic, from the DDS message-lost events of each subscription and,
while a topic has one publisher, from the gaps in its publication sequence numbers; the count
is logged as a warning at the end, returned, and written into the bag's metadata: rosbag2 has
no field for it, so it goes into ``custom_data`` under ``LOSS_KEY`` (a JSON object: every
topic of the bag -> count, zeros included, so a bag says that it was counted).

Where the ``.mcap`` differs from one ``ros2 bag record`` of Jazzy writes (the rosbags writer;
``mcap`` and ``ros2 bag`` read both): a message's publish time is its log time (rosbag2: the
publisher's source time stamp), the channels carry no ``topic_type_hash`` metadata (the hash
is in metadata.yaml), the metadata says ``ros_distro: rosbags``, and no CRC is computed
(rosbag2: the summary's); the profile, schemas, channels, chunks with message indexes, the
statistics and the ``rosbag2`` metadata record (``serialized_metadata``) are as rosbag2's.

Message definitions come from the rosbags typestore for Jazzy; types it does not know
(``psl_msgs``, or any other package's) are read from the installed ``.msg`` files, found via
``ament_index_python`` or, failing that, ``AMENT_PREFIX_PATH``.
"""

from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass
import importlib
import json
import math
import os
from pathlib import Path
import threading
import time

import rclpy
import rclpy.logging
from rclpy.duration import Duration
from rclpy.node import Node
from rclpy.qos import (
    DurabilityPolicy,
    HistoryPolicy,
    QoSProfile,
    ReliabilityPolicy,
)
from rclpy.signals import SignalHandlerOptions
from rclpy.topic_endpoint_info import TopicEndpointInfo
from rosbags.interfaces import (
    Connection,
    Nodetype,
    Qos,
    QosDurability,
    QosHistory,
    QosLiveliness,
    QosReliability,
    QosTime,
)
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import get_typestore, get_types_from_msg, Stores
from rosbags.typesys.store import Typestore

from psl_ros.bag_reading import open_bag
from psl_ros.hot_path import HotPath

# Topics never recorded when recording "all" topics.
EXCLUDED_TOPICS = frozenset({'/rosout', '/parameter_events'})
# Interface packages registered in every typestore made here.
PROJECT_INTERFACE_PACKAGES = ('psl_msgs',)
# rosbag2 metadata version written by ROS 2 Jazzy (QoS stored as a YAML list with names).
BAG_VERSION = 9
# custom_data key of metadata.yaml: JSON object, recorded topic -> messages known lost.
LOSS_KEY = 'psl.messages_lost'

_DISCOVERY_PERIOD = 0.2  # [s] between two looks at the ROS graph
# [s] rest of the taking thread after each wake-up: messages queue up in the middleware
# meanwhile (a few hundred at the loop's rate, far below what keep-all holds) and are taken
# with one wake-up instead of one each
_TAKE_PAUSE = 0.005
_WRITE_PERIOD = 0.05  # [s] between two wake-ups of the writer thread
_MAX_WAIT = 0.1  # [s] longest wait of the calling thread, bounds the reaction time to `stop`
_NODE_NAME = 'psl_bag_recorder'


# --------------------------------------------------------------------------------------------
# Message types
# --------------------------------------------------------------------------------------------

def _share_dirs(package: str) -> list[Path]:
    """Candidate share folders of an installed package, ament index first."""
    candidates = []
    try:
        from ament_index_python.packages import (
            get_package_share_directory,
            PackageNotFoundError,
        )
    except ImportError:
        pass
    else:
        try:
            candidates.append(Path(get_package_share_directory(package)))
        except PackageNotFoundError:
            pass
    for prefix in os.environ.get('AMENT_PREFIX_PATH', '').split(os.pathsep):
        if prefix:
            candidates.append(Path(prefix) / 'share' / package)
    return candidates


def _split_msgtype(msgtype: str) -> tuple[str, str, str]:
    """('package', 'msg', 'Name') of 'package/msg/Name'.

    Raises:
        ValueError: ``msgtype`` is not of that form.

    """
    parts = msgtype.split('/')
    if len(parts) != 3 or not all(parts):
        raise ValueError(f"message type {msgtype!r} is not of the form 'package/msg/Name'")
    return parts[0], parts[1], parts[2]


def _referenced_types(fielddef: tuple) -> list[str]:
    """Names of the message types a rosbags field definition refers to."""
    kind, detail = fielddef
    if kind == Nodetype.NAME:
        return [detail]
    if kind in (Nodetype.ARRAY, Nodetype.SEQUENCE):
        return _referenced_types(detail[0])
    return []


def register_msgtype(typestore: Typestore, msgtype: str) -> None:
    """Make ``msgtype`` (e.g. 'psl_msgs/msg/TaskInstance') and its dependencies known.

    Types already in the typestore are left alone; the others are parsed from their installed
    ``.msg`` files (``<share>/<package>/msg/<Name>.msg``) and registered together.

    Raises:
        LookupError: The type or one of its dependencies has no installed ``.msg`` file.
        ValueError: A type name is not of the form 'package/msg/Name'.

    """
    pending: dict = {}

    def collect(name: str) -> None:
        if name in typestore.fielddefs or name in pending:
            return
        package, subfolder, stem = _split_msgtype(name)
        paths = [share / subfolder / f'{stem}.msg' for share in _share_dirs(package)]
        path = next((p for p in paths if p.is_file()), None)
        if path is None:
            raise LookupError(f'no {package}/{subfolder}/{stem}.msg in the ament index '
                              'or under AMENT_PREFIX_PATH')
        types = get_types_from_msg(path.read_text(encoding='utf-8'), name)
        pending.update(types)
        for _constants, fields in types.values():
            for _field_name, fielddef in fields:
                for dependency in _referenced_types(fielddef):
                    collect(dependency)

    collect(msgtype)
    if pending:
        typestore.register(pending)


def make_typestore() -> Typestore:
    """The rosbags typestore for ROS 2 Jazzy plus every message of the project's packages.

    Raises:
        LookupError: A project interface package is not installed.

    """
    typestore = get_typestore(Stores.ROS2_JAZZY)
    for package in PROJECT_INTERFACE_PACKAGES:
        msg_dir = next((share / 'msg' for share in _share_dirs(package)
                        if (share / 'msg').is_dir()), None)
        if msg_dir is None:
            raise LookupError(f'interface package {package!r} is not installed (not in the '
                              'ament index nor under AMENT_PREFIX_PATH)')
        for path in sorted(msg_dir.glob('*.msg')):
            register_msgtype(typestore, f'{package}/msg/{path.stem}')
    return typestore


def import_message_class(msgtype: str) -> type:
    """The rclpy message class of a type name like 'sensor_msgs/msg/JointState'.

    Raises:
        LookupError: The module or the class does not exist.
        ValueError: ``msgtype`` is not of the form 'package/msg/Name'.

    """
    package, subfolder, name = _split_msgtype(msgtype)
    try:
        module = importlib.import_module(f'{package}.{subfolder}')
    except ImportError as exc:
        raise LookupError(f'cannot import {package}.{subfolder}: {exc}') from exc
    try:
        return getattr(module, name)
    except AttributeError:
        raise LookupError(f'{package}.{subfolder} has no message {name}') from None


# --------------------------------------------------------------------------------------------
# QoS
# --------------------------------------------------------------------------------------------

def subscription_qos(publishers: Sequence[TopicEndpointInfo]) -> QoSProfile:
    """Recording QoS compatible with every publisher, as strict as all of them allow.

    Reliable if all publishers are reliable (else best effort), transient-local if all are
    (else volatile), keep-all: a subscription that falls behind keeps what it has not taken
    (up to the middleware's resource limits) instead of overwriting it.
    """
    reliable = all(p.qos_profile.reliability == ReliabilityPolicy.RELIABLE for p in publishers)
    latched = all(p.qos_profile.durability == DurabilityPolicy.TRANSIENT_LOCAL
                  for p in publishers)
    return QoSProfile(
        history=HistoryPolicy.KEEP_ALL,
        reliability=ReliabilityPolicy.RELIABLE if reliable else ReliabilityPolicy.BEST_EFFORT,
        durability=DurabilityPolicy.TRANSIENT_LOCAL if latched else DurabilityPolicy.VOLATILE,
    )


def _qos_time(duration: Duration) -> QosTime:
    """Seconds and nanoseconds; rclpy's infinite duration (2**63 - 1 ns) becomes
    RMW_DURATION_INFINITE {9223372036, 854775807}, as rosbag2 stores it in version 9."""
    sec, nsec = divmod(duration.nanoseconds, 1_000_000_000)
    return QosTime(sec, nsec)


def offered_qos(profile: QoSProfile) -> Qos:
    """A publisher's offered QoS profile in the form rosbags writes into metadata.yaml."""
    return Qos(
        history=QosHistory[profile.history.name],
        depth=profile.depth,
        reliability=QosReliability[profile.reliability.name],
        durability=QosDurability[profile.durability.name],
        deadline=_qos_time(profile.deadline),
        lifespan=_qos_time(profile.lifespan),
        liveliness=QosLiveliness[profile.liveliness.name],
        liveliness_lease_duration=_qos_time(profile.liveliness_lease_duration),
        avoid_ros_namespace_conventions=profile.avoid_ros_namespace_conventions,
    )


# --------------------------------------------------------------------------------------------
# Recording
# --------------------------------------------------------------------------------------------

def is_hidden(topic: str) -> bool:
    """Hidden topic: a name token starts with '_' (e.g. '/fibonacci/_action/status')."""
    return any(token.startswith('_') for token in topic.split('/'))


@dataclass(frozen=True)
class Recording:
    """What `record` wrote.

    Attributes:
        path: The bag folder.
        counts: Messages written per topic (fully qualified names; a named topic never
            seen has 0).
        lost: Messages known to be lost per topic, same keys (see the module docstring).

    """

    path: Path
    counts: dict[str, int]
    lost: dict[str, int]

    @property
    def total_lost(self) -> int:
        return sum(self.lost.values())


class _Topic:
    """One recorded topic: its bag connection and what became of its messages.

    ``taken``, ``last_seq`` and ``gaps`` belong to the taking thread, ``written`` and
    ``write_failures`` to the writer thread; the totals are read after both have ended.
    """

    __slots__ = ('name', 'connection', 'handle', 'taken', 'written', 'write_failures',
                 'dds_lost', 'gaps', 'last_seq', 'sequence_usable')

    def __init__(self, name: str, connection: Connection):
        self.name = name
        self.connection = connection
        self.handle = None  # the rcl subscription
        self.taken = 0
        self.written = 0
        self.write_failures = 0
        self.dds_lost = 0  # the middleware's message-lost total
        self.gaps = 0  # messages missing between publication sequence numbers
        self.last_seq: int | None = None
        self.sequence_usable = True

    def check_sequence(self, seq: int | None) -> None:
        """Count the messages missing before publication sequence number ``seq``.

        Sequence numbers count one publisher's messages, and the message info does not say
        which publisher sent one: a jump is counted only while the topic has one publisher,
        and a number that does not increase (a second publisher interleaving, or a
        restarted one) ends the counting for the topic (the DDS events still count).
        """
        last, self.last_seq = self.last_seq, seq
        if seq is None or last is None or not self.sequence_usable:
            return
        if seq <= last:
            self.sequence_usable = False
        elif (seq > last + 1 and self.handle is not None
              and self.handle.get_publisher_count() == 1):
            self.gaps += seq - last - 1

    @property
    def lost(self) -> int:
        """Both counts see the same losses of one publisher; either may see more (events:
        any publisher; sequence: losses the middleware does not report), so the larger."""
        return max(self.dds_lost, self.gaps) + self.write_failures


class _Recorder:
    """Subscribes to topics as they appear; takes their messages in a `HotPath` thread and
    writes them to an open Writer from a queue in a writer thread."""

    def __init__(self, node: Node, writer: Writer, typestore: Typestore,
                 wanted: list[str] | None):
        self._node = node
        self._writer = writer
        self._typestore = typestore
        self._wanted = wanted  # None: every topic
        self._topics: dict[str, _Topic] = {}
        self._unrecordable: set[str] = set()  # unknown type: reported, not retried
        self._ambiguous: set[str] = set()  # more than one type: reported once, retried
        self._write_lock = threading.Lock()  # the Writer: connections added while writing
        self._write_error: Exception | None = None
        self._queue: deque = deque()  # (topic, receive time, data); appended, popped left
        self._closing = threading.Event()
        self._hot_path = HotPath(node, name='bag_recorder_take', pause=_TAKE_PAUSE)
        self._hot_path.start()
        self._writer_thread = threading.Thread(target=self._write_loop, name='bag_writer',
                                               daemon=True)
        self._writer_thread.start()

    def so_far(self) -> Recording:
        """The recording up to now: messages taken (queued or written) and known lost per
        subscribed topic."""
        entries = list(self._topics.values())
        return Recording(Path(self._writer.path),
                         {e.name: e.taken - e.write_failures for e in entries},
                         {e.name: e.lost for e in entries})

    def missing(self) -> list[str]:
        """Named topics not subscribed (yet)."""
        return [t for t in self._wanted or () if t not in self._topics]

    def never_seen(self) -> list[str]:
        """Named topics never subscribed, other than those already reported (unrecordable
        type, several types)."""
        return [t for t in self.missing()
                if t not in self._unrecordable and t not in self._ambiguous]

    def discover(self, accept_new: bool) -> None:
        """Subscribe to every wanted topic that now has publishers.

        Args:
            accept_new: In all-topics mode, whether topics not subscribed yet are taken.

        """
        available = dict(self._node.get_topic_names_and_types())
        if self._wanted is not None:
            candidates = self._wanted
        elif accept_new:
            candidates = sorted(t for t in available
                                if t not in EXCLUDED_TOPICS and not is_hidden(t))
        else:
            return
        for topic in candidates:
            if (topic in self._topics or topic in self._unrecordable
                    or topic not in available):
                continue
            publishers = self._node.get_publishers_info_by_topic(topic)
            if not publishers:
                continue
            msgtypes = sorted({p.topic_type for p in publishers})
            if len(msgtypes) > 1:
                if topic not in self._ambiguous:
                    self._ambiguous.add(topic)
                    self._node.get_logger().warning(
                        f'not recording {topic} while it is published with several types: '
                        f'{", ".join(msgtypes)}')
                continue
            try:
                self._subscribe(topic, msgtypes[0], publishers)
            except (LookupError, ValueError) as exc:
                self._unrecordable.add(topic)
                self._node.get_logger().error(f'cannot record {topic}: {exc}')

    def _subscribe(self, topic: str, msgtype: str,
                   publishers: Sequence[TopicEndpointInfo]) -> None:
        msg_class = import_message_class(msgtype)
        register_msgtype(self._typestore, msgtype)
        rihs01 = self._typestore.hash_rihs01(msgtype)
        advertised = {str(p.topic_type_hash) for p in publishers
                      if p.topic_type_hash.version == 1}
        if advertised - {rihs01}:
            self._node.get_logger().warning(
                f'{topic}: publishers advertise type hash {", ".join(sorted(advertised))} '
                f'but the installed definition of {msgtype} hashes to {rihs01}; '
                'the bag stores the installed definition')
        qos = subscription_qos(publishers)
        with self._write_lock:
            connection = self._writer.add_connection(
                topic, msgtype, typestore=self._typestore,
                offered_qos_profiles=[offered_qos(p.qos_profile) for p in publishers])
        entry = self._topics[topic] = _Topic(topic, connection)
        put = self._queue.append

        def on_message(data: bytes, info: dict) -> None:
            put((entry, info.get('received_timestamp') or time.time_ns(), data))
            entry.taken += 1
            entry.check_sequence(info.get('publication_sequence_number'))

        def on_lost(status) -> None:
            entry.dds_lost = status.total_count

        entry.handle = self._hot_path.subscribe(msg_class, topic, on_message, qos, raw=True,
                                                info=True, message_lost=on_lost)
        self._node.get_logger().info(
            f'recording {topic} [{msgtype}] ({qos.reliability.name.lower()}, '
            f'{qos.durability.name.lower()}, keep all)')

    def _write_loop(self) -> None:
        """The writer thread: every _WRITE_PERIOD, write what the queue holds; once closing,
        write the rest and end."""
        pop = self._queue.popleft
        while True:
            closing = self._closing.wait(_WRITE_PERIOD)
            while self._queue:
                entry, stamp, data = pop()
                try:
                    with self._write_lock:
                        self._writer.write(entry.connection, stamp, data)
                except Exception as exc:  # noqa: BLE001 - counted as lost, reported at the end
                    entry.write_failures += 1
                    if self._write_error is None:
                        self._write_error = exc
                        self._node.get_logger().error(f'cannot write to the bag: {exc!r}')
                else:
                    entry.written += 1
            if closing:
                return

    def close(self) -> Recording:
        """Take what the subscriptions still hold, write the queue out, close the writer
        (the bag is then complete) with the losses in its metadata, drop the subscriptions."""
        self._hot_path.stop(drain=True)
        self._closing.set()
        self._writer_thread.join()
        counts = dict.fromkeys(self._wanted or (), 0)
        lost = dict(counts)
        for name, entry in self._topics.items():
            counts[name], lost[name] = entry.written, entry.lost
        self._writer.set_custom_data(LOSS_KEY, json.dumps(
            {name: lost[name] for name in self._topics}, sort_keys=True))
        self._writer.close()
        return Recording(Path(self._writer.path), counts, lost)


def _run(recorder: _Recorder, node: Node, duration: float | None,
         stop: threading.Event | None, discovery_timeout: float, all_topics: bool,
         progress: Callable[[Recording], None] | None) -> None:
    """Discover (and report progress) until the duration is over, ``stop`` is set or the
    context is shut down."""
    start = time.monotonic()
    end = math.inf if duration is None else start + duration
    discovery_end = start + discovery_timeout
    next_look = start
    reported_missing = False
    while not (stop is not None and stop.is_set()):
        if not node.context.ok():
            _logger(node).info('recording interrupted: the ROS context was shut down')
            return
        now = time.monotonic()
        if now >= end:
            break
        if now >= next_look:
            if all_topics:
                if now < discovery_end:
                    recorder.discover(accept_new=True)
            elif recorder.missing():
                recorder.discover(accept_new=True)
                if now >= discovery_end and not reported_missing and recorder.missing():
                    reported_missing = True
                    node.get_logger().info('no publisher yet on ' + ', '.join(recorder.missing())
                                           + '; subscribing when they appear')
            next_look = now + _DISCOVERY_PERIOD
        if progress is not None:
            progress(recorder.so_far())
        wait = max(0.0, min(next_look, end, now + _MAX_WAIT) - now)
        if stop is not None:
            stop.wait(wait)
        else:
            time.sleep(wait)


def _logger(node: Node):
    """The node's logger, or after an external shutdown (which leaves it unable to publish to
    /rosout) a console-only logger."""
    if node.context.ok():
        return node.get_logger()
    return rclpy.logging.get_logger(f'{node.get_name()}.after_shutdown')


def record(output: str | Path, topics: Sequence[str] = (), *,
           duration: float | None = None, stop: threading.Event | None = None,
           discovery_timeout: float = 5.0, node: Node | None = None,
           progress: Callable[[Recording], None] | None = None) -> Recording:
    """Record topics into a new rosbag2 bag folder ``output`` (MCAP storage).

    Named topics (relative names resolve against the node's namespace) are subscribed as soon
    as they have publishers; those still missing after ``discovery_timeout`` are waited for
    during the whole recording (looked for every 0.2 s), and those never seen are reported at
    the end with count 0. With no ``topics``, every topic that has publishers within
    ``discovery_timeout`` is recorded, except /rosout, /parameter_events and hidden topics
    (a name token starting with '_'); topics appearing later are not added. A topic published
    with several types at once is not recorded (as rosbag2 does). Publishers appearing after
    a topic is subscribed do not change its QoS.

    Recording stops after ``duration`` seconds (wall clock, counted from the call), when
    ``stop`` is set, or on KeyboardInterrupt or an external rclpy shutdown (both end the
    recording normally). Every message the subscriptions hold when it stops is still written
    (for a reliable topic: every message they acknowledged before). The bag is closed
    (complete and readable) in every case. Messages known lost are logged as a warning,
    returned and stored in the metadata (`LOSS_KEY`).

    Node and rclpy: with ``node=None`` a node is created in rclpy's default context and
    destroyed at the end; if rclpy is not initialised yet, record() initialises it and shuts
    it down again at the end (only what it initialised). A given ``node`` is used and left
    alive. Either way the recording subscriptions are served by threads of the recorder, not
    by an executor: the node needs no spinning, and one that an executor spins is left to it.

    Args:
        output: Bag folder to create; must not exist.
        topics: Topic names to record; empty for all topics.
        duration: Recording time [s]; None for no limit.
        stop: Set to end the recording.
        discovery_timeout: [s] See above.
        node: Node to subscribe with; None to create one.
        progress: Called in the calling thread about every 0.1 s with the recording so far:
            per subscribed topic the messages taken (all of them are in the bag once record()
            returns) and those known lost; e.g. to set ``stop`` once everything expected
            has arrived or is known lost.

    Returns:
        The bag's path, and the messages written and known lost per topic.

    Raises:
        TypeError: ``topics`` is a single string.
        FileExistsError: ``output`` exists already.
        ValueError: ``duration`` or ``discovery_timeout`` is negative or NaN.
        LookupError: The project's interface packages are not installed.

    """
    if isinstance(topics, str):
        raise TypeError(f'topics must be a sequence of names, not the string {topics!r}')
    output = Path(output)
    if output.exists() or output.is_symlink():
        raise FileExistsError(f'{output} exists already; a bag is recorded into a new folder')
    if duration is not None and not duration >= 0.0:
        raise ValueError(f'duration must be >= 0 or None, got {duration}')
    if not discovery_timeout >= 0.0:
        raise ValueError(f'discovery_timeout must be >= 0, got {discovery_timeout}')
    typestore = make_typestore()

    initialised_here = False
    own_node = node is None
    if own_node:
        if not rclpy.ok():
            # Without rclpy's signal handlers Ctrl-C raises KeyboardInterrupt, which ends the
            # recording while the context is still valid.
            rclpy.init(signal_handler_options=SignalHandlerOptions.NO)
            initialised_here = True
        node = Node(_NODE_NAME)
    try:
        wanted = list(dict.fromkeys(node.resolve_topic_name(t) for t in topics)) or None
        writer = Writer(output, version=BAG_VERSION, storage_plugin=StoragePlugin.MCAP)
        writer.open()
        recorder = _Recorder(node, writer, typestore, wanted)
        try:
            _run(recorder, node, duration, stop, discovery_timeout, all_topics=wanted is None,
                 progress=progress)
        except KeyboardInterrupt:
            _logger(node).info('recording interrupted')
        finally:
            recording = recorder.close()
        logger = _logger(node)
        never_seen = recorder.never_seen()
        if never_seen:
            logger.warning('no publisher seen on ' + ', '.join(never_seen)
                           + '; recorded 0 messages')
        if recording.total_lost:
            logger.warning(
                f'{recording.total_lost} messages lost: '
                + ', '.join(f'{t} {n}' for t, n in recording.lost.items() if n)
                + f' (metadata.yaml custom_data {LOSS_KEY})')
        logger.info(f'wrote {sum(recording.counts.values())} messages to {output}')
        return recording
    finally:
        if own_node:
            node.destroy_node()
        if initialised_here:
            rclpy.try_shutdown()


def read_bag_summary(path: str | Path) -> dict[str, tuple[str, int]]:
    """Topic -> (message type, message count) of a rosbag2 bag (any storage rosbags reads).

    Raises:
        BagError: a ValueError naming the bag that cannot be read (`psl_ros.bag_reading`).
    """
    with open_bag(path) as reader:
        return {topic: (info.msgtype, info.msgcount) for topic, info in reader.topics.items()}
