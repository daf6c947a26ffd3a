"""Camera-path smoothing: keyframes, end-constraints and the optimal path per segment."""
from .optimal import PathParams, PathSolution, integrate, path_cost, solve_segment, zeta_bar

__all__ = ["PathParams", "PathSolution", "integrate", "path_cost", "solve_segment", "zeta_bar"]
