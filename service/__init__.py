"""The HTTP service. Imports nothing from ``worker``: the worker's Celery app is handed in. See docs/SERVICE.md.

Three modules stay at this root because they are the roots a reader starts from, each importing the packages
below it and imported by none of them:

- ``service.app``: the API process (``uvicorn --factory service.app:create_app``);
- ``service.compose``: the composition root, the one place the API and the worker's tasks build their objects;
- ``service.embedded``: ``dualphys serve``, the API plus a worker and beat on one machine.

Below them, by role: ``core/`` (settings, the Redis coordinator, the Celery message contract and task sending;
imports nothing else of the service), ``jobs/`` (a job's manifest, folder, operations, uploads and results),
``surveys/`` (watched folders), ``webhooks/`` (callbacks at a run's end), ``api/`` (routes and schemas), ``web/``
(the dashboard) and ``client/`` (the remote commands; httpx only, no pipeline beyond the job options).
"""
