"""The baselines every figure is a ratio to, kept apart from the product's kernels.

``algorithm1``: the paper's Algorithm 1 (bisection; ``method="bisect"``).
``thibaudeau``: every crossing with every boundary, sorted
(``method="thibaudeau"``). ``amanatides_woo``: Amanatides and Woo's
traversal of a Cartesian box (``logsph_trace.cartesian``), the speed the
exact traversal is measured against.
"""
