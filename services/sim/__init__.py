"""services/sim"""
