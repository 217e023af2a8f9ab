"""Play a rosbag2 into a ROS 2 graph, and record topics into one, without ros2cli / rosbag2_py.

``play_bag`` publishes every message of a rosbag2 (any the converter of :mod:`sfm_ttr_ros.ros.bag`
writes, and any other CDR rosbag2 whose message types are installed) with its recorded timing
scaled by ``rate``: the raw CDR bytes from the bag go straight to ``Publisher.publish(bytes)``
(rclpy's ``publish_raw``), so nothing is decoded or re-encoded. ``TopicRecorder`` does the
reverse: rclpy subscriptions with ``raw=True`` hand it the serialized bytes, which a
:class:`~sfm_ttr_ros.ros.bag.BagRecorder` writes as they are.

QoS. Publishers are RELIABLE, VOLATILE, KEEP_LAST ``qos_depth`` (default 100, as deep as 10 s of
KITTI at 10 Hz), like ``ros2 bag play`` on a bag without QoS metadata. A reliable DataWriter
keeps a sample until every matched reader acknowledged it, and a reader acknowledges when the
sample is in its history, so the writer's depth is not where frames get lost. Where they
can get lost is the *subscriber's* KEEP_LAST history: a subscriber whose executor falls more
than its depth behind the player overwrites its oldest unread samples. The ``refiner`` node's
callbacks only convert and queue (its depth, ``qos_depth`` = 30, is a 3 s backlog at 10 Hz), so
at ``rate`` 1 nothing is lost; play faster only into subscribers that keep up. At the end the
player waits (``ack_timeout``) until every sample is acknowledged before it leaves, so the last
frames are not lost by destroying the publishers early.

Waiting. With ``wait_for_subscribers`` the player first waits (at most ``wait_timeout`` s, then
an :class:`InputError` that says what to do) until the given ``wait_topics`` each have a matched
subscriber, or, when none are given, until any topic of the bag has one; it then lets discovery
settle for ``settle_s`` and names the topics nobody subscribes to (their messages go nowhere).
The counts are those of DDS matching (``Publisher.get_subscription_count``), not the graph.

``/clock`` (rosgraph_msgs/Clock, RELIABLE, depth 10: compatible with rclpy's best-effort
``use_sim_time`` subscription) carries the bag time when ``clock`` is set: before every message
with its log time, and at ``clock_hz`` while waiting between messages.

rclpy is imported lazily: the core (``import sfm_ttr_ros``) stays ROS-free. Player and recorder
each run in their own rclpy ``Context`` without signal handlers, so they coexist with any other
rclpy use in the process, and Ctrl-C raises KeyboardInterrupt in the caller as usual
(``play_bag`` cleans up first and raises :class:`PlaybackInterrupted`, a KeyboardInterrupt that
carries the counts).
"""

from __future__ import annotations

import importlib
import threading
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

from msg_adapters.stamp import clock_message
from sfm_ttr_ros.core.errors import InputError
from sfm_ttr_ros.ros.bag import BagRecorder, ProgressBar

DEFAULT_QOS_DEPTH = 100
CLOCK_TOPIC = "/clock"


def message_class(msgtype: str):
    """``sensor_msgs/msg/Image`` -> the installed ROS 2 Python class ``sensor_msgs.msg.Image``."""
    parts = str(msgtype).split("/")
    if len(parts) == 2:  # ROS 1 style "pkg/Type"
        parts = [parts[0], "msg", parts[1]]
    if len(parts) != 3 or not all(parts):
        raise InputError(f"bad message type name {msgtype!r}: expected pkg/msg/Type")
    pkg, kind, name = parts
    try:
        module = importlib.import_module(f"{pkg}.{kind}")
        return getattr(module, name)
    except (ImportError, AttributeError) as exc:
        raise InputError(f"message type {msgtype} is not installed in this ROS 2 environment "
                         f"({type(exc).__name__}: {exc}); install its package or leave its "
                         "topic out") from exc


def _init_context():
    import rclpy
    from rclpy.context import Context
    from rclpy.signals import SignalHandlerOptions

    ctx = Context()
    rclpy.init(context=ctx, signal_handler_options=SignalHandlerOptions.NO)
    return ctx


def _reliable_qos(depth: int):
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

    if int(depth) < 1:
        raise InputError(f"qos_depth must be >= 1, got {depth}")
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=int(depth),
                      reliability=ReliabilityPolicy.RELIABLE,
                      durability=DurabilityPolicy.VOLATILE)


@dataclass
class PlayResult:
    """What :func:`play_bag` did."""

    published: Counter = field(default_factory=Counter)  # topic -> messages
    clock: int = 0  # /clock messages
    seconds: float = 0.0  # wall time of the playback (after waiting)
    bag_seconds: float = 0.0  # bag time covered
    no_subscriber: list[str] = field(default_factory=list)  # no subscriber at the end
    unacked: list[str] = field(default_factory=list)  # topics not fully acknowledged at the end
    interrupted: bool = False

    @property
    def total(self) -> int:
        return sum(self.published.values())


class PlaybackInterrupted(KeyboardInterrupt):
    """Ctrl-C during :func:`play_bag`; ``result`` holds what was published until then."""

    def __init__(self, result: PlayResult) -> None:
        super().__init__("playback interrupted")
        self.result = result


def _open_bag(path: Path):
    from rosbags.rosbag2 import Reader

    if not path.exists():
        raise InputError(f"bag not found: {path}")
    if not (path / "metadata.yaml").is_file():
        raise InputError(f"{path} is not a rosbag2 folder (no metadata.yaml)")
    try:
        reader = Reader(path)
        reader.open()
    except Exception as exc:  # rosbags raises several error types for unreadable bags
        raise InputError(f"cannot read bag {path}: {type(exc).__name__}: {exc}") from exc
    return reader


def play_bag(
    path: str | Path,
    rate: float = 1.0,
    clock: bool = False,
    wait_for_subscribers: bool = True,
    topics: list[str] | None = None,
    progress: bool = True,
    *,
    wait_topics: list[str] | None = None,
    wait_timeout: float = 30.0,
    settle_s: float = 0.5,
    qos_depth: int = DEFAULT_QOS_DEPTH,
    clock_hz: float = 40.0,
    ack_timeout: float = 10.0,
    node_name: str = "sfm_ttr_player",
) -> PlayResult:
    """Publish the messages of the rosbag2 ``path`` (all topics, or ``topics``) in log-time
    order with their recorded timing divided by ``rate``; see the module docstring for QoS,
    waiting and ``/clock``. Returns the counts; raises :class:`InputError` for an unreadable
    bag, an unknown topic, a non-CDR connection, a message type that is not installed or no
    subscriber within ``wait_timeout``, and :class:`PlaybackInterrupted` on Ctrl-C (after
    cleaning up)."""
    path = Path(path)
    if not (rate > 0 and rate != float("inf")):
        raise InputError(f"rate must be a positive finite number, got {rate}")
    if clock and not clock_hz > 0:
        raise InputError(f"clock_hz must be positive, got {clock_hz}")
    reader = _open_bag(path)
    result = PlayResult()
    ctx = node = None
    bar = None
    try:
        conns, classes = _playable_connections(reader, path, topics, wait_topics)
        ctx = _init_context()
        import rclpy

        node = rclpy.create_node(node_name, context=ctx)
        qos = _reliable_qos(qos_depth)
        pubs = {t: node.create_publisher(cls, t, qos) for t, cls in classes.items()}
        bag_clock = _BagClock(node, result, clock_hz) if clock else None
        if wait_for_subscribers:
            _wait_for_subscribers(pubs, wait_topics, wait_timeout, settle_s, progress)
        bar = ProgressBar(sum(c.msgcount for c in conns), f"play {path.name}", enabled=progress)
        _publish_in_time(reader, conns, pubs, bag_clock, rate, result, bar)
        bar.close()
        _wait_for_acknowledgements(pubs, bag_clock, ack_timeout, result)
        return result
    except KeyboardInterrupt:
        result.interrupted = True
        if bar is not None:
            bar.close()
        raise PlaybackInterrupted(result) from None
    finally:
        if node is not None:
            node.destroy_node()
        if ctx is not None:
            import rclpy

            rclpy.try_shutdown(context=ctx)
        reader.close()


def _playable_connections(reader, path: Path, topics: list[str] | None,
                          wait_topics: list[str] | None) -> tuple[list, dict[str, type]]:
    """The bag's connections to play (``topics``, or all) and each topic's message class;
    :class:`InputError` for a topic not in the bag, a non-CDR connection, a topic with two
    types, a type that is not installed, or nothing to play."""
    conns = list(reader.connections)
    have = {c.topic for c in conns}
    for what, wanted in (("topic", topics), ("wait topic", wait_topics)):
        missing = [t for t in (wanted or []) if t not in have]
        if missing:
            raise InputError(f"{what}(s) {', '.join(missing)} not in bag {path}; it has: "
                             f"{', '.join(sorted(have)) or 'no topics'}")
    if topics is not None:
        conns = [c for c in conns if c.topic in set(topics)]
    types: dict[str, str] = {}
    for c in conns:
        fmt = getattr(c.ext, "serialization_format", "cdr")
        if fmt != "cdr":
            raise InputError(f"{c.topic} in {path} is serialized as {fmt!r}; only cdr "
                             "can be published")
        if types.setdefault(c.topic, c.msgtype) != c.msgtype:
            raise InputError(f"{c.topic} has two message types in {path}: "
                             f"{types[c.topic]} and {c.msgtype}")
    classes = {t: message_class(mt) for t, mt in types.items()}
    if sum(c.msgcount for c in conns) == 0:
        raise InputError(f"no messages to play in {path}")
    return conns, classes


class _BagClock:
    """``/clock`` carrying the bag time, published at ``clock_hz`` while the player waits."""

    def __init__(self, node, result: PlayResult, clock_hz: float) -> None:
        self.cls = message_class("rosgraph_msgs/msg/Clock")
        self.time_cls = message_class("builtin_interfaces/msg/Time")
        self.pub = node.create_publisher(self.cls, CLOCK_TOPIC, _reliable_qos(10))
        self.period = 1.0 / clock_hz
        self.result = result

    def publish(self, ns: int) -> None:
        self.pub.publish(clock_message(ns, self.cls, self.time_cls))
        self.result.clock += 1


def _publish_in_time(reader, conns: list, pubs: dict, bag_clock: _BagClock | None,
                     rate: float, result: PlayResult, bar: ProgressBar) -> None:
    """Each message at its log time (from the first one's) divided by ``rate``, preceded by
    the bag time on ``/clock`` (also ticking while waiting); counts into ``result``."""
    bag_start = None  # log time of the first message played
    wall0 = time.monotonic()
    for conn, t, raw in reader.messages(connections=conns):
        if bag_start is None:
            bag_start, wall0 = t, time.monotonic()
            span = max(0, reader.end_time - t)
        target = wall0 + (t - bag_start) / 1e9 / rate
        while True:
            now = time.monotonic()
            if now >= target:
                break
            if bag_clock is not None:
                bag_clock.publish(bag_start + int((now - wall0) * rate * 1e9))
                time.sleep(min(target - now, bag_clock.period))
            else:
                time.sleep(target - now)
        if bag_clock is not None:
            bag_clock.publish(t)
        pubs[conn.topic].publish(bytes(raw))
        result.published[conn.topic] += 1
        result.bag_seconds = (t - bag_start) / 1e9
        bar.update(result.total, f"{result.bag_seconds:.1f}/{span / 1e9:.1f} s bag time "
                   f"x{rate:g}")
    result.seconds = time.monotonic() - wall0


def _wait_for_acknowledgements(pubs: dict, bag_clock: _BagClock | None, ack_timeout: float,
                               result: PlayResult) -> None:
    """Name the topics nobody subscribes to, and wait until every subscribed topic's samples
    are acknowledged (those that are not within ``ack_timeout`` go to ``result.unacked``)."""
    from rclpy.duration import Duration

    result.no_subscriber = sorted(t for t, p in pubs.items()
                                  if p.get_subscription_count() == 0)
    clock_pub = [(CLOCK_TOPIC, bag_clock.pub)] if bag_clock is not None else []
    for t, p in [*pubs.items(), *clock_pub]:
        if p.get_subscription_count() and not p.wait_for_all_acked(
                Duration(seconds=float(ack_timeout))):
            result.unacked.append(t)


def _wait_for_subscribers(pubs: dict, wait_topics: list[str] | None, timeout: float,
                          settle_s: float, verbose: bool) -> None:
    import sys

    want = list(wait_topics) if wait_topics else None
    deadline = time.monotonic() + float(timeout)
    said = False
    while True:
        counts = {t: p.get_subscription_count() for t, p in pubs.items()}
        ready = (all(counts[t] > 0 for t in want) if want else any(counts.values()))
        if ready:
            break
        if time.monotonic() >= deadline:
            missing = [t for t in (want or pubs) if counts[t] == 0]
            what = "each of" if want else "any of"
            raise InputError(
                f"no subscriber on {what} {', '.join(missing)} after {timeout:g} s: start the "
                "subscriber (e.g. the refiner node, remapped to these topics) first, check "
                "ROS_DOMAIN_ID / ROS_AUTOMATIC_DISCOVERY_RANGE, or play without waiting")
        if verbose and not said:
            print(f"waiting for subscribers on {', '.join(want or pubs)} "
                  f"(up to {timeout:g} s)...", file=sys.stderr, flush=True)
            said = True
        time.sleep(0.05)
    time.sleep(max(0.0, float(settle_s)))  # let the subscriber's other endpoints match too


class TopicRecorder:
    """Record ROS 2 topics into a rosbag2 (raw CDR bytes, no decoding), e.g. the refiner's
    ``~/depth`` during a demo.

    ``topics`` maps topic -> message type (``{"/refiner/depth/image": "sensor_msgs/msg/Image"}``).
    Subscriptions are RELIABLE, VOLATILE, KEEP_LAST ``qos_depth`` (they do not match a
    best-effort publisher); the log time of each message is its reception time (as
    ``ros2 bag record``). The callbacks and the bag live in one spinning thread. Use as a
    context manager, or :meth:`start` / :meth:`stop`; the bag is complete after :meth:`stop`.
    """

    def __init__(self, out: str | Path, topics: dict[str, str], storage: str = "mcap",
                 qos_depth: int = DEFAULT_QOS_DEPTH, node_name: str = "sfm_ttr_recorder") -> None:
        if not topics:
            raise InputError("TopicRecorder needs at least one topic")
        self.classes = {t: message_class(mt) for t, mt in topics.items()}
        self.topics = dict(topics)
        self.out = Path(out)
        self.storage = storage
        self.qos_depth = int(qos_depth)
        self.node_name = node_name
        self.recorder: BagRecorder | None = None
        self._ctx = self._node = self._executor = self._thread = None
        self._cond = threading.Condition()
        self._last_msg = 0.0
        self._error: BaseException | None = None

    def start(self) -> TopicRecorder:
        import rclpy
        from rclpy.executors import SingleThreadedExecutor

        qos = _reliable_qos(self.qos_depth)
        try:
            self._ctx = _init_context()
            self._node = rclpy.create_node(self.node_name, context=self._ctx)
            for t, cls in self.classes.items():
                self._node.create_subscription(cls, t, self._callback(t), qos, raw=True)
            self._executor = SingleThreadedExecutor(context=self._ctx)
            self._executor.add_node(self._node)
            # The bag is opened, written (callbacks) and closed in the spinning thread: the
            # sqlite3 storage refuses to be used from another thread than its creator's.
            ready = threading.Event()
            self._thread = threading.Thread(target=self._run, args=(ready,),
                                            name="topic-recorder", daemon=True)
            self._thread.start()
            ready.wait()
            if self._error is not None:
                raise self._error
        except BaseException:
            self._teardown()
            raise
        return self

    def _run(self, ready: threading.Event) -> None:
        from rclpy.executors import ExternalShutdownException

        try:
            self.recorder = BagRecorder(self.out, self.storage)
            for t, mt in self.topics.items():
                self.recorder.add_topic(t, mt)
        except BaseException as exc:  # handed to start()
            if self.recorder is not None:
                self.recorder.abort()
            self._error = exc
            ready.set()
            return
        ready.set()
        try:
            self._executor.spin()
        except ExternalShutdownException:
            pass
        finally:
            self.recorder.close()

    def _callback(self, topic: str):
        def cb(data: bytes) -> None:
            self.recorder.write_raw(topic, data, time.time_ns())
            with self._cond:
                self._last_msg = time.monotonic()
                self._cond.notify_all()

        return cb

    @property
    def counts(self) -> dict[str, int]:
        return dict(self.recorder.counts) if self.recorder else {}

    def publisher_count(self, topic: str) -> int:
        return self._node.count_publishers(topic) if self._node else 0

    def wait_for_publishers(self, topics: list[str], timeout: float,
                            alive=lambda: True, settle_s: float = 0.5) -> list[str]:
        """Wait until a publisher of each of ``topics`` has been discovered, or ``timeout``
        s passed, or ``alive()`` turned False (the publishing process died); returns the
        topics still without a publisher.

        A VOLATILE subscription receives only what is published after the two endpoints have
        matched, so a recorder must wait for this before the data it records is produced. The
        graph shows the writer once this side discovered it; the writer's side of the match
        follows within the same discovery round, hence ``settle_s`` more once all are seen.
        """
        deadline = time.monotonic() + float(timeout)
        while True:
            missing = [t for t in topics if self.publisher_count(t) == 0]
            if not missing:
                time.sleep(settle_s)
                return []
            if time.monotonic() >= deadline or not alive():
                return missing
            time.sleep(0.05)

    def wait_for(self, counts: dict[str, int], timeout: float,
                 idle_timeout: float | None = None) -> bool:
        """Wait until each topic has at least ``counts[topic]`` messages (True), or until
        ``timeout`` s passed, or ``idle_timeout`` s passed without any message (False)."""
        deadline = time.monotonic() + float(timeout)
        with self._cond:
            self._last_msg = max(self._last_msg, time.monotonic())
            while True:
                have = self.counts
                if all(have.get(t, 0) >= n for t, n in counts.items()):
                    return True
                now = time.monotonic()
                if now >= deadline:
                    return False
                if idle_timeout is not None and now - self._last_msg >= idle_timeout:
                    return False
                self._cond.wait(timeout=min(0.1, deadline - now))

    def _teardown(self) -> None:
        import rclpy

        if self._executor is not None:
            self._executor.shutdown(timeout_sec=2.0)
        if self._thread is not None:
            self._thread.join(timeout=5.0)
        if self._node is not None:
            self._node.destroy_node()
        if self._ctx is not None:
            rclpy.try_shutdown(context=self._ctx)
        self._executor = self._thread = self._node = self._ctx = None

    def stop(self) -> dict[str, int]:
        """Stop recording and finish the bag; returns the message counts per topic."""
        self._teardown()  # the spinning thread closes the bag when the executor stops
        return self.counts

    def __enter__(self) -> TopicRecorder:
        return self.start()

    def __exit__(self, exc_type, exc, tb) -> None:
        self.stop()
