"""Tests of each substrate folder: act/ (ACT-SR on LeRobot datasets), sac/ (SAC with critic memories)."""
