"""The object store (the S3 API) beside the local data folder: workers on many hosts without a shared disk.

``objects`` is the client (boto3), ``mirror`` keeps a local folder and a key prefix in step (pull before a stage,
push what changed), ``jobs`` is the job store whose manifests, logs and files live in the object store. Built
by ``service.compose`` only when ``object_store_url`` is set; unset, nothing here is imported.
"""
