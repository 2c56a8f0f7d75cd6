"""Bringup of the nf-control stack: composed executables, process helpers, launch files."""
