"""The bundled run configurations and the thesis's data (package data of fringecal, as
``fringecal.configs``; located by :func:`fringecal.config.configs_dir`)."""
