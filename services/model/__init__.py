"""services/model"""
