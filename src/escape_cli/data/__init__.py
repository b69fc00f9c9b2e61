"""Datasets: procedural shapes of the PCN categories, depth-rendered partials, the PCN layout.

- `escape_cli.data.pcn`: read and write the PCN folder layout (used by training and eval).
- `escape_cli.data.synth`: generate a PCN-layout training set from procedural shapes.
- `escape_cli.data.shapes`, `primitives`, `surface`, `depth_views`: the pieces it uses.
"""
