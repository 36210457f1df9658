"""Personalisation: the closed-form fold-in of a person's ratings, the node's online
fold-in and fleet sharing (their state persists in ``recording.state_store``)."""
