"""asyncdonkey: an asyncio-native robot runtime that runs Donkeycar parts unchanged."""

__version__ = "0.1.0"
