"""What the stages can trust: what a drive separates, what a residual Jacobian constrains, least-squares sigma (docs/uncertainty.md)."""
