"""Simulated GelSight contacts, dual-contact scenarios and simulated phone scans."""
