"""Recordings in and out: the in-memory ``Recording``, its files (MCAP writer, reader and recovery, CDR, CSV,
rosbag2), the one loader of input files, the bounds of every number read, outputs that never destroy data,
the table's reference specific force and the progress of the sample sources read."""
