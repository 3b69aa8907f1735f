"""The base every other package builds on, importing nothing of the project: the camera model and
rotations, atomic file writing, the hand skeleton, the on-disk formats (take, frames.csv, session,
rig.toml, ground truth, DATASET.h5), config validation, every error class and the progress
protocol. docs/architecture.md has the map."""
