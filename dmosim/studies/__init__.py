"""The paper's Section IV results: the studies as DataFrames (paper.py) and their figures (figures.py)."""
