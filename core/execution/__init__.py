"""Act: the step from a chosen demo to the next state.

`apply_demo` (transfer + execute + the task's stage), `OutcomeMemo` (simulated outcomes kept for
reuse) and `expansion` (one lookahead expansion, and who runs them).
"""
