"""Seeding on the AprilTag and region growing of solved blocks, front by front."""
