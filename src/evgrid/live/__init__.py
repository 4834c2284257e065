"""evgrid on a running robot (docs/live.md)."""
