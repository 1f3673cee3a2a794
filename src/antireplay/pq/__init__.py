"""The post-quantum session protocol (ML-KEM handshake signed with ML-DSA).

:mod:`.session` is transport-free; :mod:`antireplay.mavlink.pq` carries it
over MAVLink.
"""
