"""Personalisation: the closed-form fold-in of a person's ratings, the node's online
fold-in and fleet sharing (a person's state persists through ``stars_ros.state``)."""
