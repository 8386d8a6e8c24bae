"""Sub-commands of ``endowave-cl``; see endowave_cl/cli.py."""
