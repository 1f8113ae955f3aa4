"""The pose-graph back-end, front-end agnostic: the GTSAM Pose3 graph (``pose_graph``) and its
optimisation, one pipeline of stages (``optimization``: ``least_squares``, ``loop_evidence`` with
the statistics of ``outliers``, ``robust_stage``, ``certificate_stage``), gtsam behind
``gtsam_bridge``, the SE-Sync certificate (``certificate``, ``certificate_refinement``,
``noise_model``), the running iSAM2 estimate (``incremental``), structure checks
(``graph_diagnostics``) and g2o files (``g2o``)."""
