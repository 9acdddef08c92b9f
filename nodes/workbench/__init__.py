"""Workbench node: the browser page where people act on the site (see README.md)."""
