"""How good and how fast: metrics, LPIPS, the evaluate stage, the report, re-rendering a job."""
