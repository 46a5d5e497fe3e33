"""Reading a watermark from an image: the level-2 DWT, the HiDDeN decoder and its weights files, read
windows, batched extraction, keys, identification and its p-values. Knows nothing of radiance fields;
``reader.train`` trains decoders."""
