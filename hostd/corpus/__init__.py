"""Corpus-scale codec evaluation: many textures x codecs x settings -> one row each, a
resumable store, BD-rate reports (`hostd corpus`). Nothing below this package imports it."""
