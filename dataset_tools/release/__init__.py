"""Release layouts other tools read and write: MANUS/BRICS releases, nerfstudio and COLMAP."""
