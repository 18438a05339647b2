"""The camera stage: every non-reference camera registered against the LiDAR map (or, without a LiDAR, the reference camera's triangulated features), with its guards (docs/method.md)."""
