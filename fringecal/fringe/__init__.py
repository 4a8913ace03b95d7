"""Fringe patterns: the projected sequence (contract), decoding and image stacks."""
