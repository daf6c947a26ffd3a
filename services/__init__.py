"""The streaming processes (capture, flow, motion, render), one thin module each.

Each service subscribes, calls the library (``quick_stream``), publishes and logs;
no algorithm lives here. They arrive with the streaming-service issue; until
then every stage runs in-process through the library (``quick-stream motion``).
"""
