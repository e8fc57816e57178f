"""A small least-recently-used store shared by threads (a diagnosis fits its candidates in two at once)."""

from __future__ import annotations

import threading
from collections import OrderedDict


class Recent:
    """The last ``size`` values stored, by key; the least recently used is dropped first.  Getting and storing hold a
    lock, so threads may share one."""

    def __init__(self, size: int):
        self.size = size
        self._items: OrderedDict = OrderedDict()
        self._lock = threading.Lock()

    def get(self, key, default=None):
        with self._lock:
            if key not in self._items:
                return default
            self._items.move_to_end(key)
            return self._items[key]

    def put(self, key, value) -> None:
        with self._lock:
            self._items[key] = value
            self._items.move_to_end(key)
            while len(self._items) > self.size:
                self._items.popitem(last=False)

    def __len__(self) -> int:
        return len(self._items)
