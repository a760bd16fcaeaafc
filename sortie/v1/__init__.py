"""Code generated from ``proto/sortie/v1`` by ``python -m sortie.protogen``; do not edit.

``terrain_pb2`` holds the messages of the terrain query service,
``terrain_pb2_grpc`` its stub and servicer base classes.
"""
