"""Reusable PB3A modules and agents: drivers, controllers, monitors."""
