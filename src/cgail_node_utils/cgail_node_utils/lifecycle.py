"""A lifecycle node's state, read through rclpy's public API.

rclpy 7 (Jazzy) has no public getter of a lifecycle node's state: the state lives in the node's
private ``_state_machine``. The public interface to it is the node's ``~/get_state`` service
(``lifecycle_msgs/srv/GetState``, what ``ros2 lifecycle get`` and lifecycle managers call). A
client call to it from inside the node would wait on the node's own executor (a deadlock in an
on-set-parameters callback), so :func:`lifecycle_state` does what the executor does with such a
request, in-process: it takes the node's ``GetState`` service from ``Node.services`` and calls
its ``callback`` with a new request and response (both public attributes of
``rclpy.service.Service``). The answer comes from the same rcl state machine the service reports,
transition states and error processing included; nothing is tracked alongside it, so it cannot
drift from what a lifecycle manager sees.

A lifecycle node built with ``enable_communication_interface=False`` (the launcher's ``lean``
nodes of a closed in-process rig) has no lifecycle services, so nothing public tells its state:
:func:`lifecycle_state` raises ``ValueError`` for it.
"""

from __future__ import annotations

from lifecycle_msgs.srv import GetState
from rclpy.lifecycle import LifecycleNodeMixin
from rclpy.node import Node
from rclpy.service import Service

#: The primary states of a managed node (the others are transitions: ``'configuring'``,
#: ``'cleaningup'``, ``'shuttingdown'``, ``'activating'``, ``'deactivating'``,
#: ``'errorprocessing'``).
PRIMARY_STATES = ('unconfigured', 'inactive', 'active', 'finalized')


def _get_state_service(node: Node) -> Service:
    """The node's own ``GetState`` service (``<node>/get_state``).

    Raises:
        ValueError: ``node`` is not a lifecycle node, or it has no ``GetState`` service.
    """
    name = node.get_fully_qualified_name()
    if not isinstance(node, LifecycleNodeMixin):
        raise ValueError(f'lifecycle_state: expected a lifecycle node, found '
                         f'{type(node).__name__} {name!r}')
    services = [s for s in node.services if s.srv_type is GetState]
    own = [s for s in services if s.srv_name == f'{name}/get_state']
    if own:
        return own[0]
    if len(services) == 1:  # the lifecycle service, remapped
        return services[0]
    raise ValueError(f'lifecycle_state: expected the get_state service of lifecycle node '
                     f'{name!r}, found {len(services)} GetState services (a node built with '
                     'enable_communication_interface=False has none)')


def lifecycle_state(node: Node) -> str:
    """Label of a lifecycle node's state, as its ``~/get_state`` service reports it.

    Args:
        node: a ``rclpy.lifecycle.LifecycleNode`` (or a node with ``LifecycleNodeMixin``) that
            has its lifecycle services.

    Returns:
        One of :data:`PRIMARY_STATES` (``'unconfigured'``, ``'inactive'``, ``'active'``,
        ``'finalized'``) or a transition state (``'configuring'`` ...) while a transition
        callback runs.

    Raises:
        ValueError: ``node`` is not a lifecycle node, or was built without its lifecycle
            services (``enable_communication_interface=False``).
    """
    service = _get_state_service(node)
    # what the executor does with a request: the callback fills the response and returns it
    response: GetState.Response = service.callback(GetState.Request(), GetState.Response())
    return str(response.current_state.label)
