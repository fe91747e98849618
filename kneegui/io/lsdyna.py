"""LS-DYNA keyword decks: read_deck, lossless write_deck, fresh write_model."""

from kneegui.io.lsdyna_read import DeckFile, DeckSource, read_deck
from kneegui.io.lsdyna_write import write_deck, write_model

__all__ = ["DeckFile", "DeckSource", "read_deck", "write_deck", "write_model"]
