"""The on-disk contracts: the sequence folder, calibration files, undistortion, CT
volumes and the importers of other formats. Builds on ``chisel.core`` only."""
