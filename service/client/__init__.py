"""A client of the dualphys service for another machine: the functions behind ``dualphys submit / status / jobs /
download / cancel`` (cli/main.py is the thin command line on top).

- :mod:`service.client.remote`: :class:`ServiceClient`, typed calls over httpx with the Bearer key; every
  non-2xx answer and every transport failure becomes a :class:`ClientError` with the service's stable code.
- :mod:`service.client.zipping`: a folder as a zip written while it uploads (no temporary file).
- :mod:`service.client.download`: resumable, checksum-verified downloads of a job's artifacts.
- :mod:`service.client.watch`: polling a job until it ends.
- :mod:`service.client.errors`: :class:`ClientError`, importable without httpx.

Only httpx is needed beyond what ``dualphys`` itself installs (``pip install dualphys[client]``), and only
``remote`` imports it: the commands import that module when they connect, so the rest of the CLI runs without it.
"""
