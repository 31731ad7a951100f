"""A child process with one rclpy LifecycleNode, for the lifecycle-services test.

It publishes std_msgs/String "tick <n>" at 20 Hz only while active; on_configure creates the
publisher, on_cleanup destroys it.
"""

import sys

from rclpy.lifecycle import LifecycleNode, LifecycleState, TransitionCallbackReturn
from std_msgs.msg import String

from fdi_ros.nodes.common import run_node


class Target(LifecycleNode):
    def __init__(self) -> None:
        super().__init__(sys.argv[1] if len(sys.argv) > 1 else "lc_target")
        self._pub = None
        self._timer = None
        self._n = 0

    def on_configure(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._pub = self.create_lifecycle_publisher(String, "lc_ticks", 10)
        self._timer = self.create_timer(0.05, self._tick)
        return TransitionCallbackReturn.SUCCESS

    def on_cleanup(self, state: LifecycleState) -> TransitionCallbackReturn:
        self.destroy_timer(self._timer)
        self.destroy_lifecycle_publisher(self._pub)
        self._pub = self._timer = None
        return TransitionCallbackReturn.SUCCESS

    def _tick(self) -> None:
        self._n += 1
        if self._pub is not None and self._pub.is_activated:
            self._pub.publish(String(data=f"tick {self._n}"))


if __name__ == "__main__":
    raise SystemExit(run_node(Target))
