"""Spk2ImgNet (Zhao et al., CVPR 2021): the network, its family members and its weights.

Imports nothing of training, export, the service, the clients, the bench or the CLI.
"""
