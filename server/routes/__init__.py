"""Endpoints: they parse and answer; the work is in runtime/, jobs.py and store/."""
