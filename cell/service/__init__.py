"""The long-running cell: job queue, the job's worker process, job store, keys."""
