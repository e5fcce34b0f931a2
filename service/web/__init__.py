"""The web dashboard: one HTML shell (``templates/index.html``, the job options form rendered in on the server)
and a few static files (``static/``: plain ES modules and CSS, no build step, nothing fetched from the internet).
The routes are ``service.api.routes.web``; the page talks to the same ``/v1`` API as every other client."""
