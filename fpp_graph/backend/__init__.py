"""The pose-graph back-end, front-end agnostic: the GTSAM Pose3 graph and its optimisation
(``pose_graph``), the outlier rule and the robust stage (``outliers``, ``robust_stage``), the
SE-Sync certificate (``certificate``, ``certificate_refinement``, ``noise_model``), the running
iSAM2 estimate (``incremental``), structure checks (``graph_diagnostics``) and g2o files
(``g2o``, ``graph_run``)."""
