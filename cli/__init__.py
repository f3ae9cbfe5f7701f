"""The ``m3t`` command line and what it runs outside Prefect: the background services (``m3t up / status /
down``) and the claims study (``m3t study``). It sits above ``flows``: it may start flows, no flow imports it."""
