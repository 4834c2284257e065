"""The simulator package evgrid_sim: its own tests."""
