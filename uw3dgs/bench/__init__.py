"""Experiment grids (`uw-bench`): grid.py reads GRID.yaml into cells, cell.py runs what is left of one cell,
executors.py runs cells locally or on Ray, view.py shows their progress."""
