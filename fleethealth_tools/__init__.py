"""Command-line tools that feed a running fleethealth server: ``simulate`` and ``replay``.

They speak to the server through the client package (``fleethealth_client``, in
``clients/python``) only, never through the server's code, and are reached from the
``fleethealth`` command (:func:`fleethealth_tools.commands.add_subcommands`).
"""
