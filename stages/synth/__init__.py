"""Procedural rooms with exact ground truth (`blunf synth`): scene, renderer, capture writer."""

from stages.synth.make import make_room

__all__ = ["make_room"]
