"""Body fits for captures that come without them (AVH §3.1): keypoints, triangulation, fitting."""
