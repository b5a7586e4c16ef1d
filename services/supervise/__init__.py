"""services/supervise"""
