"""The ranker as a managed (lifecycle) node, for launch files and lifecycle managers.

The same node as ``ros2 run stars_ros ranker`` (``ros.ranker``: same parameters, topics and
services), in the REP 2002 / ``ros2 lifecycle`` states: created unconfigured with its
parameters declared; ``configure`` loads the checkpoint, opens the recording and the state
store and creates the publishers (a checkpoint or key file that cannot be used fails the
transition, saying why, and the node stays unconfigured); ``activate`` creates the
subscriptions, services and timers, so it serves; ``deactivate`` removes them; ``cleanup``
closes the recording and state store. Run with ``ros2 run stars_ros managed_ranker`` (node
name ``ranker``), then ``ros2 lifecycle set /ranker configure`` and ``... activate``, or
``ros2 launch stars_ros ranker.launch.py managed:=true``.
"""
from __future__ import annotations

from rclpy.lifecycle import LifecycleNode, LifecycleState, TransitionCallbackReturn

from stars_ros.errors import StarsError
from stars_ros.node.parameters import PARAMETERS
from stars_ros.ros import usage
from stars_ros.ros.ranker import RankerParts, one_thread_per_library, serve
from stars_ros.ros.spinning import run_node


class ManagedRankerNode(RankerParts, LifecycleNode):
    """The ranker in lifecycle states; see the module docstring."""

    def __init__(self, **kwargs):
        LifecycleNode.__init__(self, 'ranker', **kwargs)
        self._declare_parameters()

    def destroy_node(self):
        """Destroy the node and its lifecycle state machine. rclpy's LifecycleNode leaves the
        machine, which holds the node's handle, and so keeps the rcl node and its /rosout
        publisher alive after ``destroy_node``: every line ``close`` then logs after a Ctrl-C
        ended in "Failed to publish log message to rosout: publisher's context is invalid"."""
        super().destroy_node()
        self._state_machine.destroy_when_not_in_use()

    def on_configure(self, state: LifecycleState) -> TransitionCallbackReturn:
        try:
            self._configure()
        except StarsError as error:  # CheckpointError, ConfigError: a file that cannot be used
            self.get_logger().error(f'configure failed, still unconfigured: {error}')
            self._unconfigure()
            return TransitionCallbackReturn.FAILURE
        return super().on_configure(state)

    def on_activate(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._activate()
        return super().on_activate(state)

    def on_deactivate(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._deactivate()
        return super().on_deactivate(state)

    def on_cleanup(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._unconfigure()
        return super().on_cleanup(state)

    def on_shutdown(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._deactivate()
        self._unconfigure()
        return super().on_shutdown(state)


def main(args=None):
    if usage.print_help_if_asked('managed_ranker', __doc__, PARAMETERS,
                                 'ros2 run stars_ros managed_ranker --ros-args -p top_k:=3 & '
                                 'ros2 lifecycle set /ranker configure && ros2 lifecycle set /ranker activate', args):
        return
    one_thread_per_library()
    run_node('managed_ranker', ManagedRankerNode, serve, (), args, close=ManagedRankerNode.close)


if __name__ == '__main__':
    main()
