"""Prefect task adapters: load refs -> call fringecal -> write outputs -> return refs."""
