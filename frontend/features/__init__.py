"""2D texture keypoints and descriptors: detection and matching (``detect``), the SURF
implementation (``surf``)."""
