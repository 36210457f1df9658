"""Personalisation: the closed-form fold-in of a person's ratings, the node's online
fold-in, its state file and fleet sharing."""
