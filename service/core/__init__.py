"""What every service process shares, below the job logic: ``settings`` (the ``DUALPHYS_*`` environment),
``coord`` (Redis: locks, cancel flags, the progress cache, idempotency claims, worker heartbeats), ``broker``
(the Celery message contract the API's producer and the workers share) and ``dispatch`` (task names, queues and
the sender of stage, scan and webhook tasks). Nothing here imports another part of the service."""
