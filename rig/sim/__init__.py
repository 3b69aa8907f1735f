"""The simulated capture cube: world, hand, objects, motions and paint, renderer, clocks.

A camera backend like the others and the ground truth for every later stage. Hand, objects
and motions: rig.sim.hand, rig.sim.objects, rig.sim.motion (docs/hand.md); ray casting and
signed distances of the primitives: rig.sim.shapes.
"""
