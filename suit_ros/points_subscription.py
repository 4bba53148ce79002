"""The detector's points and odometry subscriptions, whose reliability follows the publishers.

A best-effort reader matches every publisher but loses fragments of large clouds; a reliable
one gets every cloud but matches only reliable publishers (a reliable reader never hears a
best-effort publisher: no message, and no error either). ``points_qos`` chooses: ``auto``
(reliable when every publisher on the topic is reliable, best effort otherwise;
:func:`wanted_reliability`), ``reliable`` or ``sensor_data``. A user's
``qos_overrides.<topic>.subscription.reliability`` parameter wins over all of them. When the
wanted reliability changes the subscription is re-created, and the old one lives on for
``overlap_s`` so no cloud is lost while the new one matches (the node's mailbox takes a cloud
that arrives through both once). The odometry subscription follows its publishers the same
way, always ``auto`` (a pose that arrives twice replaces itself in the pose buffer).
"""
from __future__ import annotations

from collections.abc import Callable, Sequence
import time
from typing import Any

from rclpy.node import Node
from rclpy.qos import HistoryPolicy, QoSPolicyKind, QoSProfile, ReliabilityPolicy
from rclpy.qos_overriding_options import QoSOverridingOptions
from rclpy.subscription import Subscription
from sensor_msgs.msg import PointCloud2

from suit_ros.params import PointsQoS


def wanted_reliability(mode: PointsQoS, offered: Sequence[ReliabilityPolicy],
                       current: ReliabilityPolicy) -> ReliabilityPolicy:
    """The reliability ``points_qos`` asks for given the publishers' offered reliabilities
    (none publishing: ``current`` is kept)."""
    if mode == 'reliable':
        return ReliabilityPolicy.RELIABLE
    if mode == 'sensor_data':
        return ReliabilityPolicy.BEST_EFFORT
    if not offered:
        return current
    if all(r == ReliabilityPolicy.RELIABLE for r in offered):
        return ReliabilityPolicy.RELIABLE
    return ReliabilityPolicy.BEST_EFFORT


class FollowingSubscription:
    """The node's subscription to ``topic`` (resolved), re-created by :meth:`update`.

    :param depth: messages the reader holds until the executor takes them.
    :param msg_type: the message class (``PointCloud2``, ``Odometry``).
    :param label: what the log lines call the input (``points``, ``odometry``).
    :param setting: what they call ``mode`` (the parameter's name).
    """

    def __init__(self, node: Node, topic: str, callback: Callable[[Any], None],
                 mode: Callable[[], PointsQoS], depth: int, overlap_s: float,
                 msg_type: type = PointCloud2, label: str = 'points',
                 setting: str = 'points_qos') -> None:
        self.node, self.topic, self.callback, self.mode = node, topic, callback, mode
        self.depth, self.overlap_s = depth, overlap_s
        self.msg_type, self.label, self.setting = msg_type, label, setting
        self.reliability = ReliabilityPolicy.BEST_EFFORT
        self.retiring: list[tuple[float, Subscription]] = []
        # the first subscription declares the qos_overrides parameters with a system_default
        # reliability: any other value there is the user's override, honoured as given
        self.sub: Subscription | None = node.create_subscription(
            msg_type, topic, callback, self._qos(ReliabilityPolicy.SYSTEM_DEFAULT),
            qos_overriding_options=QoSOverridingOptions.with_default_policies())
        chosen = str(node.get_parameter(
            f'qos_overrides.{topic}.subscription.reliability').value)
        self.fixed = chosen != 'system_default'
        if self.fixed:
            self.reliability = self.sub.qos_profile.reliability
            node.get_logger().info(f'{label} reliability {chosen} (QoS override)')
            return
        node.destroy_subscription(self.sub)
        self.sub = None
        self.update()

    def _qos(self, reliability: ReliabilityPolicy) -> QoSProfile:
        return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=self.depth,
                          reliability=reliability)

    @property
    def overlapping(self) -> bool:
        """Whether a retiring subscription still receives (a cloud may arrive twice)."""
        return bool(self.retiring)

    def update(self) -> None:
        """Retire expired subscriptions; re-create the subscription when the wanted
        reliability changed."""
        now = time.monotonic()
        for sub in [s for t, s in self.retiring if t <= now]:
            self.node.destroy_subscription(sub)
        self.retiring = [(t, s) for t, s in self.retiring if t > now]
        if self.fixed and self.sub is not None:
            return
        offered = [i.qos_profile.reliability
                   for i in self.node.get_publishers_info_by_topic(self.topic)]
        wanted = wanted_reliability(self.mode(), offered, self.reliability)
        if self.sub is not None and wanted == self.reliability:
            return
        if self.sub is not None:
            self.retiring.append((now + self.overlap_s, self.sub))
        self.reliability = wanted
        # reliability is ours to choose; the other QoS overrides still apply
        options = QoSOverridingOptions([QoSPolicyKind.HISTORY, QoSPolicyKind.DEPTH,
                                        QoSPolicyKind.DURABILITY])
        self.sub = self.node.create_subscription(self.msg_type, self.topic, self.callback,
                                                 self._qos(wanted),
                                                 qos_overriding_options=options)
        self.node.get_logger().info(f'{self.label} subscription: {wanted.name.lower()} '
                                    f'({self.setting} {self.mode()})')
