"""Bounded waits for conditions nothing notifies the waiter of (a file another process writes,
a counter another thread bumps, a node discovered): poll until it holds or the time is up."""
import time


def wait_for(condition, timeout: float, interval: float = 0.02) -> bool:
    """True as soon as ``condition()`` holds, False once ``timeout`` seconds passed without."""
    deadline = time.monotonic() + timeout
    while not condition():
        if time.monotonic() >= deadline:
            return False
        time.sleep(interval)  # a poll between checks, not a wait for the condition itself
    return True
