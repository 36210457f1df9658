"""Service answers that arrive at a client which called the moment it found the service.

rmw_fastrtps sends a response only once the service's reply writer has matched the calling
client's reply reader, waiting for that at most its writer's ``max_blocking_time`` (Fast
DDS's default: 100 ms); past it the response is dropped, rclpy warns "failed to send response
(timeout): client will not receive response", and the client waits for ever. A client whose
request was matched before its reply reader was (discovery announces the two apart, and a
lost announcement is sent again only at the next heartbeat) meets exactly that. Raising
``max_blocking_time`` takes a Fast DDS XML profile, which is the user's to set, process-wide.

``resend_dropped`` sends such a response again, from a timer, after each of ``RESEND_AFTER_S``
(the client's reader has had time to be discovered), until one is sent or the client is gone
(rmw_fastrtps then reports success and sends nothing); each try waits in rmw_fastrtps for at
most ``max_blocking_time`` again. Only a dropped response costs anything: the others go out
as before, in the executor's own call.
"""
from __future__ import annotations

import warnings

DROPPED = 'failed to send response (timeout)'  # rclpy's RuntimeWarning when rmw_fastrtps drops one
RESEND_AFTER_S = (0.2, 0.5, 1.0, 2.0, 4.0)  # s after the drop, then after each try; 7.7 s in all


def resend_dropped(node, service, resend_after=RESEND_AFTER_S) -> None:
    """Make ``service`` (of ``node``) send a response rmw_fastrtps dropped again (module docstring)."""
    send, name = service.send_response, service.srv_name

    def send_or_resend(response, header):
        if not _sent(send, response, header):
            _later(node, send, (response, header), list(resend_after), name)
    service.send_response = send_or_resend  # what the executor calls with each callback's response


def _sent(send, response, header) -> bool:
    """``send(response, header)``; False when rclpy warned that the response was dropped.
    Other warnings raised meanwhile are issued again, as they were."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter('always')
        send(response, header)
    dropped = False
    for warning in caught:
        if issubclass(warning.category, RuntimeWarning) and DROPPED in str(warning.message):
            dropped = True
        else:
            warnings.warn_explicit(warning.message, warning.category, warning.filename, warning.lineno)
    return not dropped


def _later(node, send, answer: tuple, delays: list, name: str, waited: float = 0.0) -> None:
    """Try ``send(*answer)`` again after ``delays[0]``, and so on; say how it ended."""
    if not delays:
        node.get_logger().warning(f'{name}: a response could not be sent: the client that called was not '
                                  f'discovered within {waited:g} s')
        return
    timer = None

    def resend():
        node.destroy_timer(timer)
        if _sent(send, *answer):
            node.get_logger().info(f'{name}: a response the middleware had dropped was sent again '
                                   f'{waited + delays[0]:g} s later')
        else:
            _later(node, send, answer, delays[1:], name, waited + delays[0])
    timer = node.create_timer(delays[0], resend)
