"""services/edge"""
