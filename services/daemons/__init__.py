"""services/daemons"""
