"""SLAM over a recorded sequence: frame sources (``sources``), keyframes and loop closure
(``keyframes``, ``loop_closure``), the frame store, the end-to-end run (``pipeline``) and many
runs at once (``batch``)."""
