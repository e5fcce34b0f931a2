"""The job: its options, folder layout, stage table, completion markers, runner and progress (torch-free)."""
